"""Progress of the long commands: done, rate and ETA on a terminal, nothing in a log, and the
command's own prints never mixed into the progress line."""

import io
import sys

from snn_tools.campaign.run import CampaignProgress
from snn_tools.progress import Progress, eta_text, track


class Terminal(io.StringIO):
    def isatty(self):
        return True


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_the_line_gives_done_rate_and_eta_from_the_clock():
    clock, terminal = Clock(), Terminal()
    progress = Progress(10, 'runs', 'bench', stream=terminal, clock=clock, interval=0.0)
    clock.now += 2.0
    progress.advance(4)
    assert progress.line() == 'bench  4/10 runs  2.0 runs/s  ETA 0:00:03'
    assert terminal.getvalue().rsplit('\r', 1)[-1].rstrip('\x1b[K ') == progress.line()
    clock.now += 3600.0
    assert progress.eta() == (10 - 4) / (4 / 3602.0)
    assert eta_text(3725.4) == '1:02:05' and eta_text(None) == '-:--:--'


def test_nothing_is_written_and_no_stream_wrapped_when_not_a_terminal(capsys):
    log = io.StringIO()
    stdout = sys.stdout
    for _ in track(range(5), 'runs', 'bench', stream=log):
        assert sys.stdout is stdout
    campaign = CampaignProgress(stream=log)
    campaign.start(4, 0, 40)
    campaign.runs_finished(10)
    campaign.cell_finished()
    campaign.close()
    assert log.getvalue() == ''
    campaign.say('what runs')  # a message of the command, not progress: in the log too
    assert log.getvalue() == 'what runs\n'


def test_prints_inside_a_tracked_loop_erase_the_line_first_and_the_streams_come_back(capsys):
    terminal, clock = Terminal(), Clock()
    stdout, stderr = sys.stdout, sys.stderr
    for index in track(range(3), 'runs', 'bench', stream=terminal, clock=clock):
        assert sys.stdout is not stdout  # wrapped while the line is open
        clock.now += 1.0
        print(f'row {index}')
    assert sys.stdout is stdout and sys.stderr is stderr
    assert capsys.readouterr().out == 'row 0\nrow 1\nrow 2\n'
    text = terminal.getvalue()
    assert text.count('\r\x1b[K') == 3  # one erase before each row
    assert text.rsplit('\r', 1)[-1].startswith('bench  3/3 runs  1.0 runs/s  ETA 0:00:00 ')


def test_a_loop_left_early_restores_the_streams():
    stdout = sys.stdout
    for index in track(range(10), stream=Terminal()):
        if index == 2:
            break
    import gc
    gc.collect()
    assert sys.stdout is stdout
