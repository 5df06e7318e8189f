"""Datasets written in other tools' formats: pure functions of a dataset directory to files.

`nuscenes`: the nuScenes v1.0 tables, sensor files, map masks and split lists (the devkit loads them).
The COCO export of one camera's FWD labels is `sensors.dataset.to_coco`.
"""
