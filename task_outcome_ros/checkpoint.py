"""Self-describing checkpoints: ``load(path)`` alone rebuilds a working model.

A checkpoint is a ``torch.save`` of a dict of tensors and plain Python values only (so it
loads with ``weights_only=True``, which never runs code from the file):

- ``format`` / ``format_version``: identify our files and their layout,
- ``model_class``, ``model_args``, ``state_dict``: the network,
- ``input_size`` (W, H), ``normalisation``: what ``model.preprocess`` must do,
- ``label_table``: the task's ``labels.LabelTable`` as ``to_dict()`` (classes by id: name,
  colour, failure or not); the model has one output channel per class. Checkpoints made
  before tables travelled as data hold the default task's {name: id} and load as
  ``DEFAULT_TABLE``,
- ``train_config``, ``metrics``, optional ``optimizer_state`` and ``extra``,
- ``created_utc``, ``torch_version``, ``package_version``: provenance.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from task_outcome_ros import __version__
from task_outcome_ros.labels import DEFAULT_TABLE, LabelTable, LabelTableError
from task_outcome_ros.model import (
    OutcomeFCN,
    build_model,
    check_input_size,
    check_normalisation,
    input_channels,
)

FORMAT = "task_outcome_ros.checkpoint"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
MODEL_CLASSES = {"OutcomeFCN": OutcomeFCN}
# The state-dict entry of each model class's final classifier: its rows are the classes.
CLASSIFIER_WEIGHT = {"OutcomeFCN": "head.weight"}


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file and what is wrong."""


@dataclass
class LoadedCheckpoint:
    model: nn.Module                    # in eval mode, on the requested device
    model_args: dict[str, Any]
    input_size: tuple[int, int]         # (W, H) working resolution
    normalisation: dict[str, Any]
    label_table: LabelTable
    train_config: dict[str, Any]
    metrics: dict[str, Any]
    format_version: int
    path: Path
    sha256: str                         # of the file's bytes; ONNX exports record it
    created_utc: str = ""
    optimizer_state: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def to_plain(value: Any, where: str = "value") -> Any:
    """Dataclasses, paths, numpy values, tuples -> dict/list/str/int/float/bool/None.

    Raises TypeError naming the offending field, so a checkpoint never holds an object that
    ``weights_only`` loading would refuse.
    """
    # Exact builtins: subclasses (enums, torch's TorchVersion) are refused by weights_only.
    if value is None or isinstance(value, bool):
        return None if value is None else bool(value)
    for kind in (int, float, str):
        if isinstance(value, kind):
            return kind(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_plain(dataclasses.asdict(value), where)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where}: key {k!r} must be str or int")
            out[to_plain(k)] = to_plain(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [to_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where}: {type(value).__name__} cannot be stored in a checkpoint "
                    "(use plain str/int/float/bool/list/dict)")


def save(path: str | Path, model: nn.Module, *, model_args: dict[str, Any],
         input_size: tuple[int, int], normalisation: dict[str, Any],
         train_config: dict[str, Any] | Any, metrics: dict[str, Any],
         optimizer_state: dict[str, Any] | None = None,
         extra: dict[str, Any] | None = None,
         label_table: LabelTable = DEFAULT_TABLE) -> Path:
    """Write a checkpoint atomically (temp file in the same folder, then rename).

    ``label_table``: the task's classes; the model must have one output channel per class
    (ValueError otherwise), since the node names channel k ``label_table.classes[k]``."""
    path = Path(path)
    model_class = type(model).__name__
    if model_class not in MODEL_CLASSES:
        raise TypeError(f"cannot save a {model_class}; expected one of {sorted(MODEL_CLASSES)}")
    if not isinstance(label_table, LabelTable):
        raise TypeError(f"label_table must be a labels.LabelTable, got "
                        f"{type(label_table).__name__}")
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    problem = _table_mismatch(label_table, model_args, state, model_class)
    if problem:
        raise ValueError(f"cannot save {path}: {problem}")
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model_class": model_class,
        "model_args": to_plain(dict(model_args), "model_args"),
        "state_dict": state,
        "input_size": list(check_input_size(input_size)),
        "normalisation": check_normalisation(normalisation),
        "label_table": label_table.to_dict(),
        "train_config": to_plain(train_config, "train_config"),
        "metrics": to_plain(metrics, "metrics"),
        "optimizer_state": optimizer_state,
        "extra": to_plain(extra or {}, "extra"),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "torch_version": str(torch.__version__),
        "package_version": __version__,
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    try:  # prove now that load() will be able to read it
        torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    except Exception as exc:
        raise TypeError(f"checkpoint for {path} holds a value weights_only loading refuses "
                        f"(optimizer_state?): {str(exc).splitlines()[-1][:200]}") from None
    return atomic_write_bytes(path, buf.getvalue())


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Write a file so readers see the old or the new bytes, never half (temp + fsync +
    rename); readable like any file the user creates (mkstemp alone would leave it 0600,
    which an installed package's other users could not read)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _require(payload: dict, key: str, types: type | tuple[type, ...], path: Path) -> Any:
    if key not in payload:
        raise CheckpointError(f"checkpoint {path}: field '{key}' is missing")
    value = payload[key]
    if not isinstance(value, types):
        raise CheckpointError(f"checkpoint {path}: field '{key}' has type "
                              f"{type(value).__name__}, expected {types}")
    return value


def _table_mismatch(table: LabelTable, model_args: dict[str, Any], state: dict[str, Any],
                    model_class: str) -> str | None:
    """Why the network's outputs are not one per class of ``table`` (None: they are)."""
    # A model_args without the key builds the default number of classes (model.py).
    declared = model_args.get("num_classes", DEFAULT_TABLE.num_classes)
    if declared != table.num_classes:
        return (f"model_args num_classes={declared!r} but the label table has "
                f"{table.num_classes} classes {list(table.classes)}")
    weight = state.get(CLASSIFIER_WEIGHT[model_class])
    if isinstance(weight, torch.Tensor) and weight.dim() and weight.shape[0] != table.num_classes:
        return (f"the classifier's weights have {int(weight.shape[0])} outputs but the label "
                f"table has {table.num_classes} classes {list(table.classes)}")
    return None


def _read_table(payload: dict, path: Path) -> LabelTable:
    raw = _require(payload, "label_table", dict, path)
    try:
        return LabelTable.from_dict(raw)
    except LabelTableError as exc:
        raise CheckpointError(f"checkpoint {path}: unusable label table: {exc}") from None


def resolve_device(device: str) -> torch.device:
    """'cpu' | 'cuda' | 'cuda:N' | 'auto' (cuda when available) -> torch.device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cpu":
        return torch.device("cpu")
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device '{device}' requested but CUDA is not available "
                             "(use device 'cpu' or 'auto')")
        return torch.device(device)
    raise ValueError(f"device must be 'cpu', 'cuda' or 'auto', got {device!r}")


def load(path: str | Path, device: str = "cpu") -> LoadedCheckpoint:
    """Read, validate and rebuild a checkpoint; raises CheckpointError on any problem."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint file not found: {path}")
    torch_device = resolve_device(device)
    data = path.read_bytes()
    try:
        payload = torch.load(io.BytesIO(data), map_location=torch_device, weights_only=True)
    except Exception as exc:  # truncated zip, random bytes, pickled foreign classes ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"checkpoint {path} cannot be read (truncated, corrupt or not a "
                              f"torch file): {first[:200]}") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a task_outcome_ros checkpoint (expected a dict "
                              f"with format '{FORMAT}'); write one with checkpoint.save()")
    version = payload.get("format_version")
    if version not in SUPPORTED_VERSIONS:
        raise CheckpointError(f"checkpoint {path}: format_version {version!r} is not "
                              f"supported by this code (supported: {SUPPORTED_VERSIONS})")
    table = _read_table(payload, path)
    model_class = _require(payload, "model_class", str, path)
    if model_class not in MODEL_CLASSES:
        raise CheckpointError(f"checkpoint {path}: unknown model_class '{model_class}', "
                              f"expected one of {sorted(MODEL_CLASSES)}")
    model_args = _require(payload, "model_args", dict, path)
    state = _require(payload, "state_dict", dict, path)
    problem = _table_mismatch(table, model_args, state, model_class)
    if problem:
        raise CheckpointError(f"checkpoint {path}: {problem}")
    raw_size = _require(payload, "input_size", (list, tuple), path)
    raw_norm = _require(payload, "normalisation", dict, path)
    try:
        input_size = check_input_size(raw_size)
        normalisation = check_normalisation(raw_norm)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from None
    if model_args.get("in_channels") != input_channels(normalisation):
        raise CheckpointError(f"checkpoint {path}: its normalisation makes "
                              f"{input_channels(normalisation)} input channels but the model "
                              f"takes in_channels={model_args.get('in_channels')!r}")
    try:
        model = build_model(model_args)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: model_args {model_args} do not build a "
                              f"{model_class}: {exc}") from None
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {path}: weights do not fit the model built from "
                              f"model_args {model_args}: {str(exc)[:300]}") from None
    if not all(math.isfinite(float(t.float().abs().sum())) for t in state.values()
               if t.is_floating_point()):
        raise CheckpointError(f"checkpoint {path}: weights contain NaN or inf")
    model.to(torch_device).eval()
    return LoadedCheckpoint(
        model=model, model_args=dict(model_args), input_size=input_size,
        normalisation=normalisation, label_table=table,
        train_config=payload.get("train_config") or {}, metrics=payload.get("metrics") or {},
        format_version=int(version), path=path, sha256=hashlib.sha256(data).hexdigest(),
        created_utc=str(payload.get("created_utc", "")),
        optimizer_state=payload.get("optimizer_state"), extra=payload.get("extra") or {})
