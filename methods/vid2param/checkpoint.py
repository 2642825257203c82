"""Reading and writing Vid2Param checkpoints.

A checkpoint is a ``torch.save`` dict of tensors and plain Python values (loadable with
``weights_only=True``, so loading never runs pickled code):

``format``            "vid2param-checkpoint"
``format_version``    int, ``FORMAT_VERSION``
``config``            ``V2PConfig.to_dict()``
``state_dict``        network weights (older checkpoints use the names of ``RENAMED``)
``train``             training settings (includes ``data_seed``), step, wall time
``git_commit``        commit the training code was at (``"unknown"`` outside git) and ``dirty``
``source_sha256``     hash of model.py + parts.py + train.py + data.py when trained
``val_metrics``       validation metrics at the time of writing
``optimizer`` etc.    only in resumable training states, not in shipped checkpoints

Writes are atomic (temporary file in the same folder, then ``os.replace``).
"""

from __future__ import annotations

import hashlib
import subprocess
import zipfile
from pathlib import Path

import torch

from methods.vid2param.model import V2PConfig, Vid2ParamNet
from sysid_bench.core._io import atomic_write

__all__ = ["FORMAT", "FORMAT_VERSION", "RENAMED", "save_atomic", "load_checkpoint", "build_net",
           "upgrade_state_dict", "upgrade_optimizer_state", "git_info", "SHIPPED_CHECKPOINTS",
           "SHIPPED_CHECKPOINT", "SENSITIVITY_CONDITIONS", "CONDITION_CHECKPOINTS",
           "NOISE_LEVELS", "system_conditions", "shipped_conditions", "condition_path",
           "checkpoint_path", "condition_checkpoint", "record_name"]

FORMAT = "vid2param-checkpoint"
FORMAT_VERSION = 1
_HERE = Path(__file__).resolve().parent
_CKPT_DIR = _HERE / "checkpoints"
#: Shipped checkpoints by name: ``checkpoint="28x28"`` (also ``None``, the default) is the
#: paper's simulated-video model; ``"camera"`` takes 100x50 (W x H) camera-like video (motion
#: blur, black-out occlusions, dropped frames, pixel noise, a randomised floor height).
SHIPPED_CHECKPOINTS = {
    "28x28": _CKPT_DIR / "v2p_28x28.pt",
    "camera": _CKPT_DIR / "v2p_camera_100x50.pt",
    # the 28x28 model fine-tuned on videos whose parameters change every 50 frames
    "changing": _CKPT_DIR / "v2p_28x28_changing.pt",
}
#: The sensitivity experiment's conditions of the ball at the benchmark's default scale
#: (``sysid_bench.bench.cases``; a test checks the two agree), one model each, one recipe and
#: budget for all (``methods/vid2param/README.md``): ``checkpoint="sensitivity/<condition>"``
#: with ``:`` written ``_``. Another system's are :func:`system_conditions`.
SENSITIVITY_CONDITIONS = ("extrapolation:e", "extrapolation:g", "extrapolation:d",
                          "extrapolation:r", "noise:0", "noise:0.1", "noise:0.25", "noise:0.5",
                          "simplified")
#: The label-noise levels of every system's conditions (the ball's).
NOISE_LEVELS = ("0", "0.1", "0.25", "0.5")


def system_conditions(system: str) -> tuple[str, ...]:
    """The sensitivity conditions of ``system`` at the default scale: extrapolation in each of
    its parameters, the label-noise levels, and ``simplified`` where the system declares
    ``simplified_params`` (the ball's: :data:`SENSITIVITY_CONDITIONS`)."""
    from sysid_bench.core import systems

    s = systems.get(system)
    return (tuple(f"extrapolation:{p}" for p in s.params)
            + tuple(f"noise:{x}" for x in NOISE_LEVELS)
            + (("simplified",) if s.simplified_params else ()))


def condition_checkpoint(condition: str, system: str = "ball") -> str:
    """Checkpoint name of a sensitivity condition's model of ``system``, e.g.
    ``"sensitivity/noise_0.1"`` (the ball's) or ``"sensitivity/pendulum/noise_0.1"``."""
    name = condition.replace(":", "_")
    return f"sensitivity/{name}" if system == "ball" else f"sensitivity/{system}/{name}"


def condition_path(condition: str, system: str = "ball") -> Path:
    """Where the model of ``condition`` of ``system`` lives (whether or not it exists)."""
    return _CKPT_DIR / f"{condition_checkpoint(condition, system)}.pt"


def _condition_files() -> dict[str, Path]:
    """The ball's declared condition models, and every system's found on disk
    (``checkpoints/sensitivity/<system>/<condition>.pt``)."""
    out = {condition_checkpoint(c): condition_path(c) for c in SENSITIVITY_CONDITIONS}
    for f in sorted((_CKPT_DIR / "sensitivity").glob("*/*.pt")):
        out[f"sensitivity/{f.parent.name}/{f.stem}"] = f
    return out


#: Where each condition model lives (the ball's whether or not this checkout has them).
CONDITION_CHECKPOINTS = _condition_files()
# the ball's join its shipped checkpoints; another system's stay with that system's models
# (as ``_points.SYSTEM_CHECKPOINTS``), loaded by name through :func:`checkpoint_path`
SHIPPED_CHECKPOINTS.update({k: p for k, p in CONDITION_CHECKPOINTS.items()
                            if p.exists() and k.count("/") == 1})


def shipped_conditions() -> dict[tuple[str, str], str]:
    """``{(system, condition): checkpoint name}`` of every condition model in this checkout."""
    out = {}
    for name, path in CONDITION_CHECKPOINTS.items():
        if path.exists():
            parts = name.split("/")
            system = parts[1] if len(parts) == 3 else "ball"
            out[system, parts[-1].replace("_", ":", 1)] = name
    return out
#: The shipped 28x28 checkpoint (``checkpoint=None``).
SHIPPED_CHECKPOINT = SHIPPED_CHECKPOINTS["28x28"]


def checkpoint_path(checkpoint) -> Path:
    """A shipped checkpoint's name (``SHIPPED_CHECKPOINTS``, or a system's condition model in
    ``CONDITION_CHECKPOINTS``) as its path; a path as given."""
    if isinstance(checkpoint, str) and checkpoint in SHIPPED_CHECKPOINTS:
        return SHIPPED_CHECKPOINTS[checkpoint]
    if isinstance(checkpoint, str) and checkpoint in CONDITION_CHECKPOINTS:
        return CONDITION_CHECKPOINTS[checkpoint]
    return Path(checkpoint)


def record_name(checkpoint) -> str:
    """How records name ``checkpoint``: a shipped checkpoint's name for its name or for any
    path to its file (so that no machine path enters a record that may ship); another path
    as given."""
    if isinstance(checkpoint, str) and checkpoint in SHIPPED_CHECKPOINTS:
        return checkpoint
    try:
        resolved = Path(checkpoint).resolve()
    except (OSError, RuntimeError, TypeError):
        return str(checkpoint)
    for name, path in SHIPPED_CHECKPOINTS.items():
        if path.resolve() == resolved:
            return name
    return str(checkpoint)


#: Weight names of checkpoints written before the network was composed of named parts -> today's
#: (a name ending in "." renames every weight it begins).
RENAMED = {
    "conv.": "encoder.conv.",
    "phi_x.": "encoder.phi_x.",
    "kp.": "encoder.kp.",
    "kp_pos.": "keypoints.map.",
    "kp_gate": "keypoints.gate",
    "phi_z.": "recurrence.phi_z.",
    "cells.0.": "recurrence.cell.",
    "enc.": "posterior.mlp.",
    "prior.": "prior.mlp.",
    "roll_scale": "rolling.scale",
    "roll_bias": "rolling.bias",
    "roll_log_std": "rolling.log_std",
    "roll_log_half": "rolling.log_half",
    "dec_in.": "decoder.fc.",
    "deconv.": "decoder.deconv.",
}


def save_atomic(obj: dict, path) -> Path:
    """``torch.save`` to a temporary file next to ``path``, then rename over it
    (``sysid_bench.core._io.atomic_write``)."""
    return atomic_write(path, lambda tmp: torch.save(obj, tmp))


def load_checkpoint(path, *, expect_resumable: bool = False) -> dict:
    """Load and check a checkpoint; every problem is a ``ValueError`` that names the file.

    Parameters
    ----------
    path : str or Path
    expect_resumable : bool
        Also require the optimizer state of a training run.

    Returns
    -------
    dict
        The checkpoint dict (see the module docstring).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint: expected an existing file, got {str(path)!r}")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, ValueError, TypeError,
            AttributeError, KeyError, IndexError) as exc:
        raise ValueError(
            f"checkpoint: {str(path)!r} is corrupt or truncated, not a readable Vid2Param "
            f"checkpoint ({type(exc).__name__}: {str(exc)[:200]})"
        ) from exc
    except Exception as exc:  # the unpickler raises its own types for foreign content
        raise ValueError(
            f"checkpoint: {str(path)!r} could not be read as a Vid2Param checkpoint "
            f"({type(exc).__name__}: {str(exc)[:200]})"
        ) from exc
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        got = ck.get("format") if isinstance(ck, dict) else type(ck).__name__
        raise ValueError(f"checkpoint: expected format {FORMAT!r} in {str(path)!r}, got {got!r}")
    if ck.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"checkpoint: expected format_version {FORMAT_VERSION} in {str(path)!r}, "
            f"got {ck.get('format_version')!r}"
        )
    for key in ("config", "state_dict"):
        if key not in ck:
            raise ValueError(f"checkpoint: {str(path)!r} lacks {key!r}")
    if expect_resumable and "optimizer" not in ck:
        raise ValueError(f"checkpoint: {str(path)!r} holds no optimizer state to resume from")
    return ck


def _names(state_dict: dict) -> list[str]:
    """Today's names (``RENAMED``) of ``state_dict``'s weights, in its order."""
    if "cells.0.weight_ih" not in state_dict:  # written with today's names
        return list(state_dict)
    out = []
    for name in state_dict:
        for old, new in RENAMED.items():
            if name == old or (old.endswith(".") and name.startswith(old)):
                name = new + name[len(old):]
                break
        out.append(name)
    return out


def upgrade_state_dict(state_dict: dict) -> dict:
    """``state_dict`` with the weight names of today's network (``RENAMED``), same order; a
    physics prior trained before its noise read the backtest gets the gain that ignores it."""
    out = dict(zip(_names(state_dict), state_dict.values()))
    if "phys_prior.log_noise" in out and "phys_prior.skill_gain" not in out:
        out["phys_prior.skill_gain"] = torch.zeros(2)
    return out


def upgrade_optimizer_state(opt_state: dict, state_dict: dict, net) -> dict:
    """An optimizer's state saved beside ``state_dict``, reordered to ``net.parameters()``.

    An optimizer keys its per-parameter state by position. The renaming moved parameters, so
    an older training state would otherwise hand Adam's moments to other parameters (several
    are scalars: no shape check would catch it). ``state_dict``'s order is that of the
    parameters when saved (the network has no persistent buffers).
    """
    order = {name: i for i, (name, _) in enumerate(net.named_parameters())}
    saved = [order[name] for name in _names(state_dict)]
    return {"state": {saved[i]: v for i, v in opt_state["state"].items()},
            "param_groups": [{**g, "params": sorted(saved[i] for i in g["params"])}
                             for g in opt_state["param_groups"]]}


def build_net(ck: dict, path="checkpoint") -> Vid2ParamNet:
    """The network described by a loaded checkpoint, weights loaded, in eval mode.

    Raises ``ValueError`` when the weights do not match the stored config.
    """
    try:
        cfg = V2PConfig.from_dict(dict(ck["config"]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint: {str(path)!r} has an invalid config ({exc})") from exc
    net = Vid2ParamNet(cfg)
    try:
        net.load_state_dict(upgrade_state_dict(ck["state_dict"]), strict=True)
    except (RuntimeError, TypeError, AttributeError) as exc:
        raise ValueError(
            f"checkpoint: weights in {str(path)!r} do not match its config "
            f"({str(exc).splitlines()[0][:200]})"
        ) from exc
    net.eval()
    return net


def git_info() -> dict:
    """Commit and dirtiness of the repository holding this package (``unknown`` outside git)."""
    root = _HERE.parent.parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip() or "unknown"
        status = subprocess.run(
            ["git", "status", "--porcelain", "--", "methods/vid2param"], cwd=root,
            capture_output=True, text=True, timeout=10,
        ).stdout
        dirty = bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "unknown", True
    return {"commit": commit, "dirty": dirty}


def source_sha256() -> str:
    """Hash of the files that define the model and its training."""
    h = hashlib.sha256()
    for name in ("model.py", "parts.py", "train.py", "data.py"):
        p = _HERE / name
        if p.exists():
            h.update(name.encode())
            h.update(p.read_bytes())
    return h.hexdigest()
