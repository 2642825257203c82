"""An empty batch or video given to Vid2Param's identify_batch is refused with one line naming
``frames`` (bad-input turn 4: numpy's "need at least one array to concatenate", or an empty
list from vid2param-physics)."""

from __future__ import annotations

import numpy as np
import pytest

import methods
from methods.vid2param import SHIPPED_CHECKPOINT

pytestmark = pytest.mark.skipif(not SHIPPED_CHECKPOINT.exists(), reason="no shipped checkpoint")


@pytest.mark.parametrize("name", ["vid2param", "vid2param-physics", "vid2param-changing"])
@pytest.mark.parametrize("shape", [(0, 200, 28, 28), (2, 0, 28, 28)], ids=["no-video", "no-frame"])
def test_an_empty_batch_is_refused_naming_frames(name, shape):
    est = methods.get(name)
    with pytest.raises(ValueError, match=r"^frames: expected at least one .*got an empty array "
                                         r"of shape \(" + ", ".join(map(str, shape))):
        est.identify_batch(np.zeros(shape, np.uint8))

