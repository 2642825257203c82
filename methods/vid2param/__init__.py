"""Vid2Param: online system identification from video with a physics-supervised VRNN.

``Vid2Param`` is the ``Estimator`` (``methods.get("vid2param")`` loads the shipped 28x28
checkpoint; ``methods.get("vid2param", system=S, checkpoint=F)`` a model of another system,
:mod:`methods.vid2param._points`): the network followed by its named stages (``methods.vid2param.stages``; each
shipped checkpoint's list: ``describe_checkpoints()``, ``sysid-bench list --checkpoints``).
``python -m methods.vid2param.train`` trains one and fits its stages. This package, and only
this one, imports torch.
"""

from methods.vid2param.estimator import (
    FORECASTS,
    SHIPPED_CHECKPOINT,
    SHIPPED_CHECKPOINTS,
    Vid2Param,
    Vid2ParamChanging,
    Vid2ParamPhysics,
    Vid2ParamStream,
    describe_checkpoints,
)
from methods.vid2param.model import V2PConfig
from methods.vid2param.presets import PRESETS, Preset

__all__ = ["Vid2Param", "Vid2ParamChanging", "Vid2ParamPhysics", "Vid2ParamStream", "V2PConfig", "PRESETS", "Preset",
           "FORECASTS",
           "SHIPPED_CHECKPOINT", "SHIPPED_CHECKPOINTS", "describe_checkpoints"]
