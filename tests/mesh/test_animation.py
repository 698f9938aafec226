"""torchfit.mesh.animation: the animation every reader builds, and its frame selection."""
from __future__ import annotations

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
from torchfit.mesh import AnimationError, load_animation


@pytest.mark.parametrize("frames, bad", [([0, 10 ** 20], 10 ** 20), ([-1], -1), ([0, 3], 3)])
def test_a_frame_that_does_not_exist_is_named_whatever_its_size(tmp_path, frames, bad):
    """Issue 50: problem.frames=[0,99999999999999999999] was an OverflowError traceback (the
    check ran on int64); now the one line names the frame and the frames there are."""
    animation = load_animation(write_capsule(tmp_path / "capsule"))
    assert animation.n_frames == 3
    with pytest.raises(AnimationError, match=rf"frame {bad} does not exist \(the animation "
                                             r"has frames 0\.\.2\)"):
        animation.select(frames)
    chosen = animation.select([2, 0])
    assert np.array_equal(chosen.frames, animation.frames[[2, 0]])
