"""Two ways of playing compared scene by scene: paired counts and McNemar's exact test.

    python -m ldm_rl.reports.paired_evaluations A.json B.json [A2.json B2.json ...] [--labels A B] [--out table.md]
    python -m ldm_rl.reports.paired_evaluations A.json B.json --count blocks_in_bin     # bin packing: blocks packed

Each pair is two ``evaluation.json`` files of ``recipes/evaluate.py`` that played the same held-out scenes
(the same task, object count, episodes and ``scene_seed``: evaluate.py's ``seed``), e.g. one checkpoint planned
two ways (``planner.uncertainty_penalty=0`` against ``=1.0``). Their ``per_episode.success`` lists (0 / 1 per scene, in
scene order) are paired: scenes both won, only A won, only B won, neither. McNemar's exact test asks whether
"only A" and "only B" differ by more than chance (two-sided binomial on the discordant scenes, p = 1 with none).
One row per pair, then the pairs pooled (counts summed: e.g. three seeds' weights, each on the same scenes).

``--count KEY`` compares a per-episode number instead of success (``per_episode.KEY``: ``blocks_in_bin`` on bin
packing, where a full pack is rare and the blocks packed tell two ways of playing apart; ``pile_top`` there, in
metres, on the scenes both packed; ``picks_held``, ``picks``, ``length``): each way's mean per scene, the scenes
where A's number is higher, where B's is, ties, and the two-sided sign test on the scenes that differ (McNemar's
exact test is this test on 0 / 1 outcomes). A scene either file has no number for (``null``: no pile where it did
not pack) is left out of that pair.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from ldm_rl.run.outputs import atomic_write_text

SAME_SCENES = ("task", "num_objects", "episodes", "scene_seed")  # the keys two evaluations must share to be paired


@dataclass(frozen=True)
class Paired:
    """Paired outcomes of two evaluations on the same scenes."""

    both: int
    only_a: int
    only_b: int
    neither: int

    @property
    def scenes(self) -> int:
        return self.both + self.only_a + self.only_b + self.neither

    def __add__(self, other: Paired) -> Paired:
        return Paired(self.both + other.both, self.only_a + other.only_a, self.only_b + other.only_b,
                      self.neither + other.neither)

    def mcnemar_p(self) -> float:
        """Two-sided exact McNemar p-value: P(a split of the discordant scenes at least this uneven | no difference)."""
        return sign_test_p(self.only_a, self.only_b)


@dataclass(frozen=True)
class PairedCounts:
    """A per-episode number (blocks in the bin, picks that held, the pile top, …) of two evaluations on the same
    scenes, over the scenes both have one for."""

    scenes: int
    total_a: float
    total_b: float
    a_higher: int  # scenes where A's number is the larger
    b_higher: int

    @property
    def ties(self) -> int:
        return self.scenes - self.a_higher - self.b_higher

    def __add__(self, other: PairedCounts) -> PairedCounts:
        return PairedCounts(*(x + y for x, y in zip(
            (self.scenes, self.total_a, self.total_b, self.a_higher, self.b_higher),
            (other.scenes, other.total_a, other.total_b, other.a_higher, other.b_higher))))

    def sign_p(self) -> float:
        """Two-sided sign test on the scenes whose counts differ (p = 1 with none)."""
        return sign_test_p(self.a_higher, self.b_higher)


def sign_test_p(wins_a: int, wins_b: int) -> float:
    """Two-sided exact sign test: P(a split of ``wins_a + wins_b`` fair coins at least this uneven)."""
    n = wins_a + wins_b
    tail = sum(math.comb(n, k) for k in range(min(wins_a, wins_b) + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def pair(a: list[int], b: list[int]) -> Paired:
    """Paired counts of two per-scene success lists (0 / 1, same scenes in the same order)."""
    if len(a) != len(b):
        raise ValueError(f"per-scene lists of different lengths: {len(a)} and {len(b)}")
    if any(v not in (0, 1) for v in (*a, *b)):
        raise ValueError("per-scene successes must be 0 or 1")
    both = sum(x and y for x, y in zip(a, b))
    only_a = sum(x and not y for x, y in zip(a, b))
    only_b = sum(y and not x for x, y in zip(a, b))
    return Paired(both, only_a, only_b, len(a) - both - only_a - only_b)


def pair_counts(a: list[float | None], b: list[float | None]) -> PairedCounts:
    """Paired comparison of two per-scene lists of a non-negative number (a count, or a pile top in metres), same
    scenes in the same order; a scene with ``None`` in either list (no pile where it did not pack) is left out."""
    if len(a) != len(b):
        raise ValueError(f"per-scene lists of different lengths: {len(a)} and {len(b)}")
    bad = [v for v in (*a, *b) if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))
                                                     or not math.isfinite(v) or v < 0)]
    if bad:
        raise ValueError(f"per-scene numbers must be finite and non-negative (or null), got {bad[0]!r}")
    kept = [(x, y) for x, y in zip(a, b) if x is not None and y is not None]
    if not kept:
        raise ValueError("no scene has a number in both lists: nothing to compare")
    return PairedCounts(len(kept), sum(x for x, _ in kept), sum(y for _, y in kept),
                        sum(x > y for x, y in kept), sum(y > x for x, y in kept))


def read(path: Path, key: str = "success") -> dict:
    """One ``evaluation.json`` with its per-scene outcomes ``per_episode[key]``."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable evaluation.json ({type(err).__name__}: {err})") from None
    if "per_episode" not in data:
        raise ValueError(f"{path}: no per_episode outcomes (written by recipes/evaluate.py from 2026-11-28 on)")
    if not isinstance(data["per_episode"], dict):
        raise ValueError(f"{path}: per_episode must be a mapping of per-scene lists")
    if not isinstance(data["per_episode"].get(key), list):
        have = ", ".join(sorted(data["per_episode"])) or "none"
        raise ValueError(f"{path}: per_episode.{key} must be a list with one entry per scene (it has: {have})")
    missing = [name for name in SAME_SCENES if name not in data]
    if missing:
        raise ValueError(f"{path}: lacks {', '.join(missing)}, needed to check that two evaluations played the "
                         "same scenes")
    return data


def paired_files(path_a: Path, path_b: Path, count: str | None = None) -> Paired | PairedCounts:
    """Paired outcomes of two evaluation.json files: successes (:class:`Paired`) or, given ``count``, that
    per-episode count (:class:`PairedCounts`); refuses two that did not play the same scenes."""
    key = count or "success"
    a, b = read(path_a, key), read(path_b, key)
    differ = [f"{name} {a[name]!r} vs {b[name]!r}" for name in SAME_SCENES if a[name] != b[name]]
    if differ:
        raise ValueError(f"{path_a} and {path_b} played different scenes: {'; '.join(differ)}")
    return (pair_counts if count else pair)(a["per_episode"][key], b["per_episode"][key])


def name(path: Path) -> str:
    """A file's name in the table: its run folder for an ``evaluation.json``, else its stem."""
    return path.parent.name if path.name == "evaluation.json" else path.stem


def table(rows: list[tuple[str, Paired]], label_a: str, label_b: str) -> str:
    """Markdown: one row per pair and the pooled row."""
    lines = [f"| pair | scenes | {label_a} | {label_b} | both | only {label_a} | only {label_b} | neither "
             "| McNemar p |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, p in rows:
        lines.append(f"| {name} | {p.scenes} | {p.both + p.only_a} | {p.both + p.only_b} | {p.both} | {p.only_a} | "
                     f"{p.only_b} | {p.neither} | {p.mcnemar_p():.3g} |")
    return "\n".join(lines) + "\n"


def count_table(rows: list[tuple[str, PairedCounts]], label_a: str, label_b: str, count: str) -> str:
    """Markdown for a per-episode number: one row per pair and the pooled row (``scenes``: those both have one)."""
    lines = [f"| pair | scenes | {label_a}: mean {count} | {label_b}: mean {count} | {label_a} higher | "
             f"{label_b} higher | equal | sign test p |",
             "|---|---|---|---|---|---|---|---|"]
    for name, p in rows:
        lines.append(f"| {name} | {p.scenes} | {p.total_a / p.scenes:.4g} | {p.total_b / p.scenes:.4g} | {p.a_higher} | "
                     f"{p.b_higher} | {p.ties} | {p.sign_p():.3g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.paired_evaluations", description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", type=Path, help="evaluation.json files, in pairs: A B [A B ...]")
    parser.add_argument("--labels", nargs=2, default=["A", "B"], metavar=("A", "B"),
                        help="names of the two ways of playing")
    parser.add_argument("--out", type=Path, default=None, help="also write the table to this markdown file")
    parser.add_argument("--count", default=None, metavar="KEY",
                        help="compare this per-episode number (blocks_in_bin, pile_top, picks_held, picks, length), "
                             "not success")
    args = parser.parse_args(argv)
    if len(args.files) % 2:
        parser.error(f"evaluation.json files come in pairs (A B ...); got {len(args.files)}")
    try:
        rows = [(f"{name(a)} / {name(b)}", paired_files(a, b, args.count))
                for a, b in zip(args.files[::2], args.files[1::2])]
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if len(rows) > 1:
        pooled = rows[0][1]
        for _, p in rows[1:]:
            pooled = pooled + p
        rows.append(("pooled", pooled))
    text = count_table(rows, *args.labels, args.count) if args.count else table(rows, *args.labels)
    print(text, end="")
    if args.out is not None:
        atomic_write_text(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
