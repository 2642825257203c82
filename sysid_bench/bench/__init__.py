"""The benchmark suite: the experiments over every method, a resumable results store, runners.

Modules
-------
cases           scales (smoke / default / paper), test cases, input kinds
store           the SQLite results store (long-format rows, one transaction per cell)
experiment      the Experiment / Cell protocol and shared helpers
identification  1. identification vs observed frames
forecasting     2. forward prediction
changing        3. parameters that change every 50 frames
sensitivity     4. extrapolation, label noise, simplified physics (methods that train)
calibration     5. coverage / NLL of posteriors and agreement with the nuts reference
foreign         6. MuJoCo videos: physics that is not ours (the paper's real videos)
online          7. the cost of a posterior after every frame
interception    8. the paper's robot experiment, simulated (intercept/: the task's parts)
camera          9. camera footage: clips filmed as a camera would, with their truth
systems         0. every method on every system, one table across systems
runner          builds the grid and runs it on a process pool or a Dask cluster
"""

from __future__ import annotations

from sysid_bench.bench.calibration import Calibration
from sysid_bench.bench.camera import Camera
from sysid_bench.bench.changing import Changing
from sysid_bench.bench.experiment import EXPERIMENTS
from sysid_bench.bench.forecasting import Forecasting
from sysid_bench.bench.foreign import Foreign
from sysid_bench.bench.identification import Identification
from sysid_bench.bench.interception import Interception
from sysid_bench.bench.online import Online
from sysid_bench.bench.sensitivity import Sensitivity
from sysid_bench.bench.systems import Systems

#: name -> experiment, in report order (the dict lives in .experiment, which runs a cell by
#: name without importing this package's modules back)
EXPERIMENTS.update(
    (e.name, e) for e in (Systems(), Identification(), Forecasting(), Changing(), Sensitivity(),
                       Calibration(), Foreign(), Online(), Interception(), Camera())
)

__all__ = ["EXPERIMENTS"]
