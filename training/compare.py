"""``python -m training compare A B``: two models on the same images, paired.

A and B are two ``evaluate`` results (eval.json, or the folder holding it) on the same data
and split, or two ``robustness`` results (robustness.json, or its folder) on the same data
and scenes; two run folders whose manifests are identical hold the same data. For each set
of images it prints both all-correct rates with their 95 % intervals, the images only one
model got wrong, and the exact McNemar p-value (training/stats.py); for a robustness result,
also each point's Holm-adjusted p-value over the points with a paired test, the one a rule
about "no point worse beyond chance" should name (training/stats.py says why). Results
written before the suite recorded its mistakes per point can still be compared by rate,
without the paired test.
"""

from __future__ import annotations

from pathlib import Path

from training.config import load_json
from training.stats import holm_adjusted, paired_comparison, rate_with_interval

RESULT_FILES = ("eval.json", "robustness.json")


def load_result(path: Path) -> tuple[str, dict]:
    """("eval" | "robustness", report) from a result file or the folder that holds one."""
    path = Path(path)
    if path.is_dir():
        found = [path / name for name in RESULT_FILES if (path / name).is_file()]
        if len(found) != 1:
            raise FileNotFoundError(f"{path}: expected one of {', '.join(RESULT_FILES)}, "
                                    f"found {len(found)}")
        path = found[0]
    report = load_json(path)
    if "factors" in report:
        return "robustness", report
    if "image_all_correct" in report and "mistakes" in report:
        return "eval", report
    raise ValueError(f"{path}: neither an evaluate nor a robustness result")


def _same(a: dict, b: dict, keys: tuple[str, ...], what: str) -> None:
    for key in keys:
        if a.get(key) != b.get(key) and not (key == "data"
                                             and same_dataset(a.get(key), b.get(key))):
            raise ValueError(f"not the same images: {what} {key} {a.get(key)!r} vs "
                             f"{b.get(key)!r}; compare results made on the same data")


def same_dataset(a: str | None, b: str | None) -> bool:
    """Two run folders hold the same images when their manifests (every image's files and
    seeds) are byte for byte the same: a run that links another's dataset to train a second
    recipe on it, or a copy. Paths are read as recorded, relative to where this runs."""
    if not (a and b):
        return False
    manifests = [Path(a) / "manifest.json", Path(b) / "manifest.json"]
    return (all(m.is_file() for m in manifests)
            and manifests[0].read_bytes() == manifests[1].read_bytes())


def compare_reports(kind_a: str, a: dict, kind_b: str, b: dict) -> list[dict]:
    """One row per set of images both results scored: its name and the paired comparison
    (or, without recorded mistakes, the two rates and intervals only)."""
    if kind_a != kind_b:
        raise ValueError(f"cannot compare an {kind_a} result with a {kind_b} result")
    if kind_a == "eval":
        _same(a, b, ("data", "split", "n_images"), "evaluation")
        row = paired_comparison(a["mistakes"], b["mistakes"], a["n_images"])
        return [{"set": f"{a['split']} of {a['data']}", **row}]
    _same(a, b, ("data", "images"), "robustness")
    rows, seen_as_trained = [], False
    for factor, entry_a in a["factors"].items():
        entry_b = b["factors"].get(factor)
        if entry_b is None:
            continue
        for k, value in enumerate(entry_a["values"]):
            if value not in entry_b["values"]:
                continue
            j = entry_b["values"].index(value)
            # Each factor's first value is the training condition: the same scenes rendered
            # the same way under every factor, so it is reported once.
            if k == 0 and j == 0:
                if seen_as_trained:
                    continue
                seen_as_trained, name = True, "as trained"
            else:
                name = f"{factor} {value}"
            n = a["images"]
            if "mistakes" in entry_a and "mistakes" in entry_b:
                rows.append({"set": name, **paired_comparison(entry_a["mistakes"][k],
                                                              entry_b["mistakes"][j], n)})
                continue
            # The stored rate is rounded to 4 digits; the image count it stands for is not.
            rights = (round(entry_a["image_all_correct"][k] * n),
                      round(entry_b["image_all_correct"][j] * n))
            rows.append({"set": name, "images": n, "p_value": None,
                         **{side: rate_with_interval(r, n) for side, r in zip("ab", rights)}})
    if not rows:
        raise ValueError("the two robustness results share no stress point")
    tested = [row for row in rows if row["p_value"] is not None]
    if len(tested) > 1:
        for row, adjusted in zip(tested, holm_adjusted(r["p_value"] for r in tested)):
            row["p_holm"] = adjusted
    return rows


def unpaired_points(a: dict, b: dict) -> tuple[list[str], list[str]]:
    """The stress points (``factor value``) only robustness result ``a`` holds and those only
    ``b`` holds: ``compare_reports`` pairs the others, and a rule over "every suite point"
    must know when a point, such as one added to the suite since, went unpaired."""
    def points(report: dict) -> set[str]:
        return {f"{factor} {value}" for factor, entry in report["factors"].items()
                for value in entry["values"][1:]}    # the first: the training condition

    only_a, only_b = points(a) - points(b), points(b) - points(a)
    return sorted(only_a), sorted(only_b)


def format_row(row: dict) -> str:
    def rate(side: dict) -> str:
        lo, hi = side["ci95"]
        return f"{side['all_correct']:.3f} [{lo:.3f}, {hi:.3f}]"

    text = f"{row['set']}: A {rate(row['a'])}, B {rate(row['b'])} ({row['images']} images)"
    if row["p_value"] is None:
        return text + "; mistakes not recorded per image, no paired test"
    return (text + f"; only A wrong {len(row['only_a_wrong'])}, only B wrong "
            f"{len(row['only_b_wrong'])}, both {row['both_wrong']}; McNemar p = "
            f"{row['p_value']:.3g}"
            + (f" (Holm over the points: {row['p_holm']:.3g})" if "p_holm" in row else ""))


def run_compare(path_a: Path, path_b: Path) -> list[dict]:
    (kind_a, a), (kind_b, b) = load_result(path_a), load_result(path_b)
    rows = compare_reports(kind_a, a, kind_b, b)
    print(f"A = {path_a}\nB = {path_b}")
    for row in rows:
        print(format_row(row))
    if kind_a == "robustness":
        for side, names in zip("AB", unpaired_points(a, b)):
            if names:
                print(f"not compared, only in {side}: {', '.join(names)}")
    return rows
