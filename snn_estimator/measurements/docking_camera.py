"""``docking_camera``: a camera on a pattern of retro-reflectors on the target (a videometer,
the Video Guidance Sensor), measuring range and line of sight from contact to a few tens of
metres. Relative attitude is not measured: the state has none.

h and H are range_azimuth_elevation's (the same geometry, frames and angles: base.py); what
differs is the noise. A pinhole camera of focal length f (pixels) sees a pattern of size b (m)
at range r as s = f b / r pixels, so r = f b / s and a centroid noise sigma_px gives

    sigma_r = r^2 sigma_px / (f b),    sigma_theta = sigma_px / f

(the depth-from-disparity law of a stereo pair, Z^2 dd / (f B), with the pattern's size in
place of the baseline). The range noise grows as r^2, the angles' stays constant. R as given is
the floor (sigma_r0 at contact, the angles' sigma); :meth:`noise_at` adds (r^2 sigma_px / (f b))^2
to the range variance at the true range. Defaults: 1024 px across a 30 deg field of view (f =
1911 px), sigma_px = 0.2 px (sub-pixel centroids of bright spots), b = 0.5 m: 2.2 cm at 10 m,
19 cm at 30 m (docs/sensors.md, "The docking camera", gives the source of each value).
"""

from __future__ import annotations

from .spherical import RangeAzimuthElevation

#: Focal length in pixels: 1024 px across a 30 deg full field of view, 512 / tan(15 deg).
FOCAL_LENGTH_PX = 1911.0
#: Centroid noise of one spot, pixels (1 sigma).
CENTROID_NOISE_PX = 0.2
#: Size of the target pattern (the spots' baseline), m.
PATTERN_BASELINE = 0.5


class DockingCamera(RangeAzimuthElevation):
    name = 'docking_camera'
    range_noise_exponent = 2
    #: sigma_px / (f b), 1/m: sigma_r = r^2 times this (2.09e-4 / m).
    default_range_noise_growth = CENTROID_NOISE_PX / (FOCAL_LENGTH_PX * PATTERN_BASELINE)
