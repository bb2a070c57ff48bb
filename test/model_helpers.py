"""Checkpoints whose answers are known by construction, for tests of the node and the tools.

A random-init network labels a scene almost uniformly (one class everywhere), so a test that
compares two decodings of the same depth through it proves nothing. These models are built
weight by weight instead:

- ``make_checkpoint(favour=c)``: class ``c`` wins on every valid pixel; with ``table`` (e.g.
  ``SHELF_TABLE``) the model has that task's classes, as one trained on it would;
- ``make_depth_band_checkpoint``: ``success`` where the depth is beyond ``BAND_SPLIT_M``,
  ``fell_outside`` where it is nearer. Its labels follow the depth values, so a byte-order,
  padding or scale mistake changes them.

No rclpy here, so unit tests can use them too.
"""

from __future__ import annotations

from pathlib import Path

import torch

from task_outcome_ros import checkpoint, model
from task_outcome_ros.labels import DEFAULT_TABLE, LabelTable

# The depth channel is (z - offset_m) / scale_m; the band model splits at its zero.
BAND_SPLIT_M = float(model.DEFAULT_NORMALISATION["offset_m"])
BAND_FAR = DEFAULT_TABLE.outcome_ids["success"]
BAND_NEAR = DEFAULT_TABLE.outcome_ids["fell_outside"]

# Another task's table, as discovery would write it for a shelf: one success-like outcome and
# three failure modes, so ids and names differ from the default task's from id 2 on.
SHELF_TABLE = LabelTable.build("shelf", [("on_shelf", False), ("fell_off", True),
                                         ("hanging_over_edge", True), ("tipped", True)])


# The default task's camera envelope as a checkpoint's dataset config carries it (only the
# fields task_outcome_ros.envelope reads), for models whose frames should be checked.
DEFAULT_ENVELOPE_CONFIG = {"task": "default", "camera": {
    "width": 640, "height": 480, "focal_px": [525.0, 590.0], "distance": [1.6, 2.4]}}


def model_args(table: LabelTable = DEFAULT_TABLE) -> dict:
    """The default architecture with one output per class of ``table``."""
    return {**model.DEFAULT_MODEL_ARGS, "num_classes": table.num_classes}


def _save(path: Path, net: torch.nn.Module, dataset: dict | None = None,
          table: LabelTable = DEFAULT_TABLE) -> Path:
    return checkpoint.save(path, net, model_args=model_args(table),
                           input_size=model.DEFAULT_INPUT_SIZE,
                           normalisation=dict(model.DEFAULT_NORMALISATION),
                           train_config={"dataset": dataset} if dataset else {}, metrics={},
                           label_table=table)


def make_checkpoint(path: Path, favour: int | None = None, seed: int = 0,
                    dataset: dict | None = None, table: LabelTable = DEFAULT_TABLE) -> Path:
    """A random-init checkpoint; ``favour`` = a class id whose head bias wins everywhere;
    ``dataset`` (e.g. DEFAULT_ENVELOPE_CONFIG): the training envelope frames are checked
    against (None: unchecked); ``table``: the task's classes (the model's outputs)."""
    torch.manual_seed(seed)
    net = model.build_model(model_args(table))
    if favour is not None:
        with torch.no_grad():
            net.head.weight.mul_(0.01)
            net.head.bias.zero_()
            net.head.bias[favour] = 10.0
    return _save(path, net, dataset, table)


def make_depth_band_checkpoint(path: Path) -> Path:
    """The U-Net wired as a depth threshold: only the stem and the last fuse block carry
    weights, passing relu(+z) and relu(-z) of the depth channel z to the head."""
    net = model.build_model(dict(model.DEFAULT_MODEL_ARGS))
    net.eval()
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):  # identity in eval mode
                m.weight.fill_(1.0)
                m.running_mean.zero_()
                m.running_var.fill_(1.0)
        conv0, conv1 = net.stem[0], net.stem[3]
        conv0.weight[0, 0, 1, 1], conv0.weight[1, 0, 1, 1] = 1.0, -1.0  # relu(z), relu(-z)
        conv1.weight[0, 0, 1, 1] = conv1.weight[1, 1, 1, 1] = 1.0
        width0 = net.head.in_channels
        fuse = net.fuse[0][0]  # input: cat([upsampled deeper features (zero), stem skip])
        fuse.weight[0, width0, 1, 1] = fuse.weight[1, width0 + 1, 1, 1] = 1.0
        net.head.weight[BAND_FAR, 0, 0, 0] = 100.0
        net.head.weight[BAND_NEAR, 1, 0, 0] = 100.0
        net.head.bias[0] = 1.0  # background only within 1 cm of the split
    return _save(path, net)
