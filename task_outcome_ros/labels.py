"""A task's vocabulary: class ids, outcome names, colours, presence rule (docs/interface.md §3).

A task's label table is data: 0 background, 1 the fixture, then one id per discovered outcome,
the success-like one first (255 ignore). Discovery writes it (``discovery.json``), the dataset
manifest and every checkpoint carry it, and the node, the overlay, the bag tools and the
evaluation read it from the checkpoint. ``DEFAULT_TABLE`` is the default task's table
(success 2, fell_outside 3, stuck_on_rim 4), which checkpoints made before tables travelled
as data also use. Training, evaluation, the node and the tools import these; never copy a
constant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BACKGROUND = 0
FIXTURE = 1
FIRST_OUTCOME_ID = 2
IGNORE = 255

# Colours for overlays and figures (paper Fig. 1: green success, yellow/red failures): the
# success-like outcome takes SUCCESS_COLOUR, failure modes the palette in id order.
BACKGROUND_COLOUR = (0, 0, 0)
FIXTURE_COLOUR = (70, 130, 255)
IGNORE_COLOUR = (110, 110, 110)
SUCCESS_COLOUR = (40, 200, 60)
FAILURE_PALETTE: tuple[tuple[int, int, int], ...] = (
    (255, 210, 0), (230, 30, 30), (255, 120, 0), (200, 0, 200), (0, 200, 200),
    (140, 80, 255), (150, 90, 40), (255, 150, 190))

# Presence rule: at least PRESENCE_MIN_PIXELS labelled pixels at 640 x 480, scaled with area.
PRESENCE_MIN_PIXELS = 50
REFERENCE_PIXELS = 640 * 480


class LabelTableError(ValueError):
    """A label table that cannot be used (the message says what is wrong)."""


@dataclass(frozen=True)
class LabelTable:
    """Class names by id, which outcomes are failure modes, and a colour per id."""

    classes: tuple[str, ...]                  # id -> name: background, fixture, outcomes...
    failures: tuple[str, ...]                 # the outcome names that are failure modes
    colours: tuple[tuple[int, int, int], ...]  # id -> RGB

    @classmethod
    def build(cls, fixture: str, outcomes: list[tuple[str, bool]]) -> LabelTable:
        """A table for ``outcomes`` [(name, is_failure)], success-like ones first, each
        keeping its order; colours from the palette."""
        ordered = [o for o in outcomes if not o[1]] + [o for o in outcomes if o[1]]
        names = ["background", fixture] + [name for name, _ in ordered]
        colours = [BACKGROUND_COLOUR, FIXTURE_COLOUR]
        failures = [name for name, failure in ordered if failure]
        for name, failure in ordered:
            colours.append(FAILURE_PALETTE[failures.index(name) % len(FAILURE_PALETTE)]
                           if failure else SUCCESS_COLOUR)
        return cls(tuple(names), tuple(failures), tuple(colours)).check()

    def check(self) -> LabelTable:
        if len(self.classes) < FIRST_OUTCOME_ID + 1 or len(self.classes) > IGNORE:
            raise LabelTableError(f"a label table needs background, a fixture and 1 to "
                                  f"{IGNORE - FIRST_OUTCOME_ID} outcomes, got {self.classes}")
        if len(set(self.classes)) != len(self.classes) or not all(
                isinstance(n, str) and n for n in self.classes):
            raise LabelTableError(f"class names must be distinct non-empty strings, got "
                                  f"{self.classes}")
        if not set(self.failures) <= set(self.outcome_names):
            raise LabelTableError(f"failures {self.failures} must be outcomes of "
                                  f"{self.outcome_names}")
        if len(self.colours) != len(self.classes):
            raise LabelTableError("a label table needs one colour per class")
        return self

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def fixture_name(self) -> str:
        return self.classes[FIXTURE]

    @property
    def outcome_names(self) -> tuple[str, ...]:
        """The outcomes in id order; outcome ``outcome_names[k]`` has id FIRST_OUTCOME_ID + k."""
        return self.classes[FIRST_OUTCOME_ID:]

    @property
    def outcome_ids(self) -> dict[str, int]:
        return {name: FIRST_OUTCOME_ID + k for k, name in enumerate(self.outcome_names)}

    @property
    def success_outcomes(self) -> tuple[str, ...]:
        return tuple(n for n in self.outcome_names if n not in self.failures)

    def colour_map(self) -> dict[int, tuple[int, int, int]]:
        return {**dict(enumerate(self.colours)), IGNORE: IGNORE_COLOUR}

    def to_dict(self) -> dict:
        """Plain data for JSON files, checkpoints and the node's status."""
        return {"classes": [{"id": i, "name": name, "colour": list(self.colours[i]),
                             "failure": name in self.failures}
                            for i, name in enumerate(self.classes)]}

    @classmethod
    def from_dict(cls, data) -> LabelTable:
        """From ``to_dict``'s form, or the {name: id} form checkpoints had before tables
        travelled as data (which must then be the default task's)."""
        if isinstance(data, dict) and "classes" not in data:
            if data != LEGACY_DEFAULT_IDS:
                raise LabelTableError(f"a {{name: id}} label table must be the default task's "
                                      f"{LEGACY_DEFAULT_IDS}, got {data}")
            return DEFAULT_TABLE
        try:
            rows = sorted(data["classes"], key=lambda row: int(row["id"]))
            if [int(row["id"]) for row in rows] != list(range(len(rows))):
                raise LabelTableError(f"class ids must run 0..{len(rows) - 1}")
            return cls(tuple(str(r["name"]) for r in rows),
                       tuple(str(r["name"]) for r in rows if r.get("failure")),
                       tuple(tuple(int(c) for c in r["colour"]) for r in rows)).check()
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, LabelTableError):
                raise
            raise LabelTableError(f"not a label table ({exc!r}): {data!r:.200}") from None


DEFAULT_TABLE = LabelTable.build("container", [("success", False), ("fell_outside", True),
                                               ("stuck_on_rim", True)])
LEGACY_DEFAULT_IDS = {name: i for i, name in enumerate(DEFAULT_TABLE.classes)}


def presence_threshold(height: int, width: int,
                       min_pixels: int = PRESENCE_MIN_PIXELS) -> int:
    """Pixel count an outcome needs to be *present* in an image of this size (>= 1)."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height} x {width}")
    if min_pixels < 1:
        raise ValueError(f"presence min_pixels must be >= 1, got {min_pixels}")
    return max(1, scale_pixel_count(min_pixels, height, width))


def scale_pixel_count(pixels: int, height: int, width: int) -> int:
    """A pixel count given at 640 x 480 (REFERENCE_PIXELS), scaled with the image area."""
    return int(round(pixels * height * width / REFERENCE_PIXELS))


def outcome_pixel_counts(labels: np.ndarray, table: LabelTable = DEFAULT_TABLE
                         ) -> dict[str, int]:
    """Number of pixels per outcome in a label image."""
    labels = np.asarray(labels, dtype=np.uint8)
    # One comparison per outcome beats one bincount here (0.06 vs 0.38 ms at 640 x 480).
    return {name: int(np.count_nonzero(labels == i)) for name, i in table.outcome_ids.items()}


def outcomes_present(labels: np.ndarray, min_pixels: int = PRESENCE_MIN_PIXELS,
                     table: LabelTable = DEFAULT_TABLE) -> dict[str, bool]:
    """The paper's presence decision for each outcome (threshold scaled to the image size)."""
    h, w = labels.shape[:2]
    return presence_from_counts(outcome_pixel_counts(labels, table),
                                presence_threshold(h, w, min_pixels))


def presence_from_counts(counts: dict[str, int], threshold: int) -> dict[str, bool]:
    """The presence rule on per-outcome pixel counts already made (``outcome_pixel_counts``)."""
    return {name: count >= threshold for name, count in counts.items()}


def colourise(labels: np.ndarray, table: LabelTable = DEFAULT_TABLE) -> np.ndarray:
    """Label image -> RGB uint8 image using the table's colours (unknown ids black)."""
    lut = np.zeros((256, 3), np.uint8)
    for class_id, rgb in table.colour_map().items():
        lut[class_id] = rgb
    return lut[np.asarray(labels, dtype=np.uint8)]


def presence_scores(truth: np.ndarray, pred: np.ndarray,
                    names: tuple[str, ...] = DEFAULT_TABLE.outcome_names) -> dict:
    """The paper's image-level metric over N images: (N, K) boolean presence arrays, columns in
    ``names`` order (a table's outcome_names) -> all-correct rate, per-outcome counts and
    presence precision/recall, and the two rates again as ``presence_precision`` /
    ``presence_recall`` {outcome: rate}."""
    truth, pred = np.asarray(truth, bool), np.asarray(pred, bool)
    out: dict = {"image_all_correct": float(np.mean(np.all(truth == pred, axis=1)))
                 if len(truth) else 0.0}
    for k, name in enumerate(names):
        tp = int(np.sum(truth[:, k] & pred[:, k]))
        fp = int(np.sum(~truth[:, k] & pred[:, k]))
        fn = int(np.sum(truth[:, k] & ~pred[:, k]))
        out[name] = {"presence_precision": tp / (tp + fp) if tp + fp else 1.0,
                     "presence_recall": tp / (tp + fn) if tp + fn else 1.0,
                     "support": int(truth[:, k].sum()), "false_positives": fp,
                     "false_negatives": fn}
    for rate in ("presence_precision", "presence_recall"):
        out[rate] = {name: out[name][rate] for name in names}
    return out
