"""Export a checkpoint to ONNX beside it (``outcome_fcn.pt`` -> ``outcome_fcn.onnx``).

The graph takes the fixed working size of the checkpoint, ``input`` (N, C, h, w) float32
(C = the model's ``in_channels``) and
gives ``logits`` (N, num_classes, h, w). Its metadata records the SHA-256 of the source
checkpoint, so ``OutcomeSegmenter(backend='auto')`` uses the ONNX file only when it was made
from exactly that checkpoint, and the label table (``LabelTable.to_dict()`` as JSON) that
names the logits' channels; exports from before tables travelled as data have none and are
the default task's.

    python -m task_outcome_ros.onnx_export task_outcome_ros/models/outcome_fcn.pt
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from task_outcome_ros.checkpoint import atomic_write_bytes, load
from task_outcome_ros.labels import DEFAULT_TABLE, LabelTable

META_SOURCE_SHA256 = "source_checkpoint_sha256"
META_INPUT_SIZE = "input_size"
META_FORMAT = "format"
META_LABEL_TABLE = "label_table"
ONNX_FORMAT = "task_outcome_ros.onnx/1"
DEFAULT_OPSET = 17


def onnx_path_for(checkpoint_path: str | Path) -> Path:
    """Where the ONNX twin of a checkpoint lives: same folder and stem, ``.onnx``."""
    return Path(checkpoint_path).with_suffix(".onnx")


def read_metadata(onnx_path: str | Path) -> dict[str, str]:
    """The custom metadata of an ONNX file (empty dict if it has none).

    Read through onnxruntime, so a robot needs the runtime only; ``onnx`` is for exporting."""
    return session_metadata(_cpu_session(str(onnx_path)))


def session_metadata(session: Any) -> dict[str, str]:
    """The custom metadata of an onnxruntime InferenceSession's model."""
    return dict(session.get_modelmeta().custom_metadata_map)


def metadata_label_table(metadata: dict[str, str]) -> LabelTable:
    """The label table an export records; DEFAULT_TABLE for an export without one (made
    before tables travelled as data, so from a default-task checkpoint). LabelTableError
    (a ValueError) for a malformed one."""
    text = metadata.get(META_LABEL_TABLE)
    if text is None:
        return DEFAULT_TABLE
    try:
        return LabelTable.from_dict(json.loads(text))
    except json.JSONDecodeError as exc:
        raise ValueError(f"ONNX metadata '{META_LABEL_TABLE}' is not JSON: {exc}") from None


def _cpu_session(model: str | bytes, options: Any = None) -> Any:
    import onnxruntime as ort

    return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])


def export_onnx(checkpoint_path: str | Path, onnx_path: str | Path | None = None, *,
                opset: int = DEFAULT_OPSET, verify: bool = True) -> Path:
    """Export (legacy TorchScript exporter: no onnxscript needed), tag, check, write atomically.

    With ``verify`` the ONNX graph is run in onnxruntime on a random input and its argmax
    labels must match torch's on >= 99.9 % of pixels.
    """
    import onnx

    ckpt = load(checkpoint_path, device="cpu")
    out = Path(onnx_path) if onnx_path is not None else onnx_path_for(checkpoint_path)
    w, h = ckpt.input_size
    channels = int(ckpt.model_args["in_channels"])
    dummy = torch.zeros(1, channels, h, w)
    buf = tempfile.SpooledTemporaryFile()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about shape arithmetic in forward()
        torch.onnx.export(ckpt.model, (dummy,), buf, input_names=["input"],
                          output_names=["logits"], opset_version=opset, dynamo=False,
                          dynamic_axes={"input": {0: "batch"}, "logits": {0: "batch"}})
    buf.seek(0)
    proto = onnx.load_model_from_string(buf.read())
    table_json = json.dumps(ckpt.label_table.to_dict(), separators=(",", ":"))
    for key, value in ((META_SOURCE_SHA256, ckpt.sha256), (META_INPUT_SIZE, f"{w}x{h}"),
                       (META_FORMAT, ONNX_FORMAT), (META_LABEL_TABLE, table_json)):
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()
    if verify:
        _verify(data, ckpt.model, channels, h, w)
    return atomic_write_bytes(out, data)


def _verify(model_bytes: bytes, model: torch.nn.Module, channels: int, h: int, w: int) -> None:
    sess = _cpu_session(model_bytes)
    x = torch.randn(2, channels, h, w, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        ref = model(x).argmax(1).numpy()
    got = sess.run(["logits"], {"input": x.numpy()})[0].argmax(1)
    agree = float(np.mean(ref == got))
    if agree < 0.999:
        raise RuntimeError(f"ONNX export disagrees with torch on {100 * (1 - agree):.2f} % "
                           "of pixels")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--out", type=Path, default=None,
                        help="ONNX path (default: beside the checkpoint, .onnx)")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET)
    args = parser.parse_args(argv)
    path = export_onnx(args.checkpoint, args.out, opset=args.opset)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
