"""Monte-Carlo campaigns: the cells of a spec, their run on Dask, the tables and the interactive
page."""
