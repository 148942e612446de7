"""The web viewer (viser): Gaussians, SLAM map points, trajectories and keyframes in a browser.

`config` (the typed `viewer` group), `scene` (the snapshot records and their geometry),
`server` (the viser server and its drawing thread), `live` (the training callback and the
tracking hook), `run_folder` (a finished or interrupted run read back); `python -m segs.view`
composes them. viser is imported only when a server starts (the `viewer` extra).
"""
