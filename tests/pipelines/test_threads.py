"""accel_bayes.threads: the thread count inside a pipeline call is set and restored."""
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.threads import torch_threads


def test_torch_threads_sets_and_restores():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError):
        with torch_threads(1):
            raise RuntimeError("boom")
    assert torch.get_num_threads() == before  # restored on an exception too
    with torch_threads(None):
        assert torch.get_num_threads() == before
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(UserError, match="threads"):
            with torch_threads(bad):
                pass


def test_calibrate_refuses_bad_threads_before_reading_the_recording(tmp_path):
    from accel_bayes.pipelines.calibrate import calibrate

    with pytest.raises(UserError, match="threads"):
        calibrate(tmp_path / "missing.nc", threads=0)
