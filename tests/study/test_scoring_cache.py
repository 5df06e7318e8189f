"""`study.engine.scoring.frame_ground_truth`: every method scored on a dataset reads one copy of each
frame's ground truth, equal to `ground_truth`'s, read-only, and gone with its reader."""

import gc

import numpy as np
import pytest

from sensors.dataset import DatasetReader
from sensors.generate import GenerateConfig
from study.engine import scoring


@pytest.fixture(scope="module")
def data(shared_dataset):  # the dataset of tests/study/test_train.py: generated once per session
    return shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))


def test_ground_truth_is_computed_once_per_reader_and_equals_the_direct_one(data):
    reader = DatasetReader(data)
    for i in range(len(reader)):
        meta = {**reader.meta(i), "dataset_index": i}
        for protocol in ("reference", "visible"):
            direct = scoring.ground_truth(reader.labels(i), "camera_right", None, meta, protocol)
            first = scoring.frame_ground_truth(reader, meta, "camera_right", None, protocol)
            assert scoring.frame_ground_truth(reader, meta, "camera_right", None, protocol) is first
            assert set(first) == set(direct)
            for k in direct:
                np.testing.assert_array_equal(first[k], direct[k])
                assert not first[k].flags.writeable  # shared by every method: nobody may edit it
    # the two protocols are two entries, not one
    meta = {**reader.meta(0), "dataset_index": 0}
    assert (scoring.frame_ground_truth(reader, meta, "camera_right", None, "reference")
            is not scoring.frame_ground_truth(reader, meta, "camera_right", None, "visible"))
    key = id(reader)
    assert key in scoring._GROUND_TRUTH
    del reader
    gc.collect()
    assert key not in scoring._GROUND_TRUTH  # a later reader at the same id starts empty
