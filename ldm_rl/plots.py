"""Figures from tensors and plain rows (never models): every picture the recipes write.

=================================  ==========================================  ==============================
function                           picture                                     written by
=================================  ==========================================  ==============================
:func:`plot_prediction_grid`       before | predicted | true | |error| rows    ``recipes/train_dynamics.py``
:func:`plot_success_rate`          held-out SR (%) against iterations          ``recipes/train_dynamics.py``
:func:`plot_expert_strip`          one expert episode, frame by frame          ``recipes/render_expert_strip.py``
:func:`plot_learning_curve`        greedy SR with 95 % interval, 2 panels      ``recipes/train_policy.py``
:func:`plot_decision`              heightmap, Q map, N candidates, values      ``recipes/evaluate.py``
:func:`plot_episodes_gif`          episodes: before | predicted | real next    ``recipes/evaluate.py``
=================================  ==========================================  ==============================

Inputs are torch tensors or numpy arrays; heightmaps are ``[H, W]`` or ``[1, H, W]`` metres (row ↔ x,
column ↔ y, 3.125 mm per pixel); actions are ``(row, col, rotation bin)`` with angle ``bin·π/R``, the
fingers closing along (row, col) direction ``(cos θ, sin θ)``. Each function writes its file atomically
and returns the matplotlib ``Figure`` (already closed; its axes, titles and labels stay readable).

matplotlib is an optional extra: ``pip install 'ldm_rl[plot]'``. Without it every function raises
:class:`PlotDependencyError` (an ``ImportError``) with that one line; this module imports without it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["PlotDependencyError", "require_matplotlib", "plot_prediction_grid", "plot_success_rate",
           "plot_expert_strip", "plot_learning_curve", "plot_decision", "plot_episodes_gif"]

PLOT_EXTRA = "pip install 'ldm_rl[plot]'"
HEIGHT_CMAP, ERROR_CMAP, Q_CMAP = "viridis", "Reds", "magma"
# heights are drawn on a square-root scale: a single 2.5 cm block on a 0.25 m scale sits at 0.32 of the colour
# map (blue-green), not at 0.1 (the dark purple of the empty table)
HEIGHT_GAMMA = 0.5


def _height_norm(max_height: float):
    """The colour scale of every heightmap: 0 → ``max_height`` metres on a square-root scale."""
    from matplotlib.colors import PowerNorm

    return PowerNorm(HEIGHT_GAMMA, vmin=0.0, vmax=max_height)
PICK_COLOUR, PLACE_COLOUR, CHOSEN_COLOUR = "white", "black", "red"
RIGHT_COLOUR, WRONG_COLOUR = "tab:green", "tab:red"
PIXELS_NOTE = "128 × 128 px heightmaps, 3.125 mm per px (rows ↔ x, columns ↔ y)"


class PlotDependencyError(ImportError):
    """matplotlib (the ``plot`` extra) is not installed."""


def _bins(num_rotations: int | None) -> int:
    """R rotation bins: the given count, else the package default (``ldm_rl.geometry.NUM_ROTATIONS``)."""
    if num_rotations:
        return int(num_rotations)
    from ldm_rl.geometry import NUM_ROTATIONS

    return NUM_ROTATIONS


def require_matplotlib() -> None:
    """Raise :class:`PlotDependencyError` (one line naming the extra) unless matplotlib imports."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise PlotDependencyError(f"matplotlib is not installed: {PLOT_EXTRA} to draw figures") from None


# ------------------------------------------------------------------------------------------ helpers


def _figure(width: float, height: float):
    """A pyplot-free Figure (no global state, any backend) with constrained layout."""
    require_matplotlib()
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def _save(fig, path: str | Path, suffix: str, dpi: float) -> Path:
    from ldm_rl.run.outputs import atomic_path

    path = Path(path)
    if path.suffix.lower() != suffix:
        raise ValueError(f"figure path must end in {suffix}, got {str(path)!r}")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=suffix[1:], dpi=dpi)
    return path


def _array(x: Any, name: str, ndim: int | None = None, dtype=np.float32) -> np.ndarray:
    """A tensor/array/list -> numpy ``dtype``; ``ndim`` checks the rank (a leading 1 is squeezed first)."""
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy() if x.is_floating_point() else x.detach().cpu().numpy()
    a = np.asarray(x)
    if ndim is not None:
        while a.ndim > ndim and a.shape[0] == 1:
            a = a[0]
        if a.ndim != ndim:
            raise ValueError(f"{name} must have {ndim} dimensions (a leading 1 allowed), got shape {a.shape}")
    return a.astype(dtype, copy=False)


def _images(x: Any, name: str) -> np.ndarray:
    """[N, H, W] or [N, 1, H, W] -> [N, H, W] float32."""
    a = _array(x, name)
    if a.ndim == 4 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 3:
        raise ValueError(f"{name} must be [N, H, W] or [N, 1, H, W] heights in metres, got shape {a.shape}")
    return a


def _actions(x: Any, name: str, n: int | None = None) -> np.ndarray:
    a = _array(x, name, dtype=np.int64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
        want = f"[{n if n is not None else 'N'}, 3]"
        raise ValueError(f"{name} must be {want} (row, col, rotation bin), got shape {a.shape}")
    return a


def _flags(x: Any, name: str, n: int) -> np.ndarray | None:
    if x is None:
        return None
    a = _array(x, name, dtype=bool).reshape(-1)
    if a.shape[0] != n:
        raise ValueError(f"{name} must hold {n} flags, got {a.shape[0]}")
    return a


def _degrees(rot: int, num_rotations: int) -> float:
    return 180.0 * int(rot) / num_rotations


def action_text(action: Sequence[int], num_rotations: int) -> str:
    """``(row, col, bin)`` -> ``"r 64, c 40, 45°"``."""
    row, col, rot = (int(v) for v in action)
    return f"r {row}, c {col}, {_degrees(rot, num_rotations):g}°"


def _draw_action(ax, action: Sequence[int], num_rotations: int, colour: str, size: float = 9.0, lw: float = 1.6,
                 label: str | None = None, marker: str = "o") -> list:
    """A ring at the action pixel and a bar along the fingers' closing direction; returns the artists."""
    from matplotlib import patheffects

    row, col, rot = (int(v) for v in action)
    theta = math.pi * rot / num_rotations
    dx, dy = size * math.sin(theta), size * math.cos(theta)  # image x = column, y = row
    outline = [patheffects.withStroke(linewidth=lw + 1.5, foreground=_contrast(colour))]
    bar = ax.plot([col - dx, col + dx], [row - dy, row + dy], color=colour, lw=lw, solid_capstyle="round",
                  path_effects=outline, scalex=False, scaley=False)[0]
    ring = ax.plot([col], [row], marker=marker, ms=size * 0.8, mfc="none", mec=colour, mew=lw, ls="none", label=label,
                   path_effects=outline, scalex=False, scaley=False)[0]
    return [bar, ring]


def _contrast(colour: str) -> str:
    """The outline colour that keeps ``colour`` visible on any colour map."""
    return "white" if colour == "black" else "black"


def _heights_colourbar(fig, image, axes, **kw):
    return fig.colorbar(image, ax=axes, label="height above the table (m)", **kw)


def _no_ticks(ax) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def _pixel_axes(ax) -> None:
    ax.set_xlabel("column (y), px")
    ax.set_ylabel("row (x), px")


# ------------------------------------------------------------------------------ dynamics model


def plot_prediction_grid(before, predicted, true, actions, path: str | Path, *, max_height: float,
                         is_pick=None, correct=None, num_rotations: int | None = None, title: str | None = None,
                         dpi: float = 100):
    """Rows of dynamics predictions: before | predicted next | true next | |predicted − true|.

    Args:
        before, predicted, true: ``[N, 1, H, W]`` (or ``[N, H, W]``) heightmaps, metres.
        actions: ``[N, 3]`` (row, col, rotation bin), drawn on every tile.
        max_height: top of the height colour scale (m), the task's ``max_height``.
        is_pick: ``[N]`` bool, True for picks (hand empty before the action); labels the rows.
        correct: ``[N]`` bool, the metric's verdict (``ldm_rl.world_model.metrics.transition_metrics``' ``correct``).

    The three height columns share one colour bar in metres; the error column has its own colour map
    and colour bar in millimetres (square-root scale, so millimetre errors show beside centimetre ones).
    """
    from matplotlib.colors import PowerNorm

    num_rotations = _bins(num_rotations)
    b, p, t = _images(before, "before"), _images(predicted, "predicted"), _images(true, "true")
    if not b.shape == p.shape == t.shape or b.shape[0] < 1:
        raise ValueError(f"before, predicted and true must share one [N>=1, H, W] shape, got {b.shape}, {p.shape}, {t.shape}")
    n = b.shape[0]
    acts = _actions(actions, "actions", n)
    picks, verdicts = _flags(is_pick, "is_pick", n), _flags(correct, "correct", n)
    error_mm = 1000.0 * np.abs(p - t)
    vmax_err = max(float(error_mm.max()), 1.0)
    fig = _figure(11.0, 2.3 * n + 0.9)
    axes = fig.subplots(n, 4, squeeze=False)
    columns = ("before", "predicted next", "true next", "|predicted − true|")
    for i in range(n):
        for j, image in enumerate((b[i], p[i], t[i])):
            im_h = axes[i, j].imshow(image, cmap=HEIGHT_CMAP, norm=_height_norm(max_height), interpolation="nearest")
        im_e = axes[i, 3].imshow(error_mm[i], cmap=ERROR_CMAP, norm=PowerNorm(0.5, vmin=0.0, vmax=vmax_err),
                                 interpolation="nearest")
        pick = None if picks is None else bool(picks[i])
        for j in range(4):
            _draw_action(axes[i, j], acts[i], num_rotations, "black" if j == 3 else (PLACE_COLOUR if pick is False else PICK_COLOUR),
                         size=6, lw=1.0)
            _no_ticks(axes[i, j])
            if i == 0:
                axes[i, j].set_title(columns[j])
        axes[i, 3].text(0.02, 0.98, f"max {error_mm[i].max():.0f} mm", transform=axes[i, 3].transAxes, va="top",
                        fontsize=8, bbox={"facecolor": "white", "alpha": 0.7, "lw": 0})
        kind = "" if pick is None else ("pick" if pick else "place")
        verdict = "" if verdicts is None else ("right" if verdicts[i] else "wrong")
        label = "\n".join(s for s in (kind, f"({action_text(acts[i], num_rotations)})", verdict) if s)
        colour = "black" if verdicts is None else (RIGHT_COLOUR if verdicts[i] else WRONG_COLOUR)
        axes[i, 0].set_ylabel(label, color=colour, fontsize=9)
    _heights_colourbar(fig, im_h, axes[:, :3], shrink=min(1.0, 0.9 / n + 0.4))
    fig.colorbar(im_e, ax=axes[:, 3], label="|error| (mm)", shrink=min(1.0, 0.9 / n + 0.4))
    fig.suptitle(title or "Dynamics model: predicted vs true next heightmap")
    fig.supxlabel(f"{PIXELS_NOTE}; ring = action pixel, bar = fingers' closing direction; right / wrong = the "
                  "held-out SR rule", fontsize=8)
    _save(fig, path, ".png", dpi)
    return fig


def plot_success_rate(rows: Sequence[Mapping[str, float]], path: str | Path, *, title: str | None = None,
                      dpi: float = 120):
    """Held-out action success rate (%) against training iterations: all transitions, picks, places.

    ``rows``: dicts with ``iteration`` and the fractions ``sr``, ``sr_pick``, ``sr_place`` (NaN = none);
    with ``floor_sr`` / ``floor_sr_pick`` / ``floor_sr_place`` in the last row (``ldm_rl.world_model.metrics``' trivial
    predictors on the same transitions) each floor is drawn dashed in its series' colour.
    """
    if not rows:
        raise ValueError("rows is empty: nothing to plot")
    fig = _figure(6.5, 4.2)
    ax = fig.subplots()
    it = [r["iteration"] for r in rows]
    floors = False
    for key, label in (("sr", "all transitions"), ("sr_pick", "picks"), ("sr_place", "places")):
        line = ax.plot(it, [100.0 * float(r[key]) for r in rows], marker="o", ms=3, label=label)[0]
        floor = rows[-1].get(f"floor_{key}")
        if floor is not None and floor == floor:
            ax.axhline(100.0 * float(floor), color=line.get_color(), ls="--", lw=1.0, alpha=0.8)
            floors = True
    if floors:
        ax.plot([], [], color="0.4", ls="--", lw=1.0, label="floor (trivial predictor)")
    ax.axhline(0.0, color="0.35", lw=0.9, zorder=0)
    ax.axhline(100.0, color="0.35", lw=0.9, ls=":", zorder=0)
    ax.set_ylim(-5.0, 105.0)
    ax.set_xlabel("training iteration (gradient steps)")
    ax.set_ylabel("held-out action success rate (%)")
    ax.set_title(title or "Dynamics model: held-out action success rate")
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    _save(fig, path, ".png", dpi)
    return fig


# ------------------------------------------------------------------------------ environments


def plot_expert_strip(frames, actions, path: str | Path, *, max_height: float, num_rotations: int | None = None,
                      is_pick=None, title: str | None = None, panel_inches: float = 2.2, max_columns: int = 8,
                      dpi: float = 100):
    """One episode frame by frame: the heightmap before each step with its action, then the final state.

    Args:
        frames: ``[T+1, H, W]`` (or ``[T+1, 1, H, W]``) heightmaps, metres.
        actions: ``[T, 3]`` (row, col, rotation bin).
        is_pick: ``[T]`` bool (hand empty before the step); default: even steps are picks.
        panel_inches: side of one frame; frames wrap into balanced rows of at most ``max_columns``.
    """
    num_rotations = _bins(num_rotations)
    f = _images(frames, "frames")
    t = f.shape[0] - 1
    acts = _actions(actions, "actions", t) if t > 0 else np.zeros((0, 3), np.int64)
    picks = _flags(is_pick, "is_pick", t) if is_pick is not None else np.arange(t) % 2 == 0
    nrows = math.ceil((t + 1) / max(1, max_columns))
    cols = math.ceil((t + 1) / nrows)
    fig = _figure(panel_inches * cols + 0.8, panel_inches * nrows + 0.8)
    axes = fig.subplots(nrows, cols, squeeze=False)
    for k, ax in enumerate(axes.flat):
        if k > t:
            ax.axis("off")
            continue
        im = ax.imshow(f[k], cmap=HEIGHT_CMAP, norm=_height_norm(max_height), interpolation="nearest")
        _no_ticks(ax)
        if k < t:
            kind = "pick" if picks[k] else "place"
            _draw_action(ax, acts[k], num_rotations, PICK_COLOUR if picks[k] else PLACE_COLOUR)
            ax.set_title(f"step {k + 1}: {kind}", fontsize=10)
            ax.set_xlabel(f"({action_text(acts[k], num_rotations)})", fontsize=8)
        else:
            ax.set_title("final state", fontsize=10)
    _heights_colourbar(fig, im, axes, shrink=0.8 if nrows == 1 else 0.6)
    fig.suptitle(title or f"Expert episode: {t} steps")
    fig.supxlabel(f"{PIXELS_NOTE}; each frame is the heightmap before the step; ring = action pixel, bar = "
                  "fingers' closing direction (white = pick, black = place)", fontsize=8)
    _save(fig, path, ".png", dpi)
    return fig


# ------------------------------------------------------------------------------------- agents


def plot_learning_curve(rows: Sequence[Mapping[str, float]], path: str | Path, *, title: str | None = None,
                        dpi: float = 110):
    """Greedy success rate (%) with its 95 % interval against training episodes and wall-clock minutes.

    ``rows``: the curve rows of ``recipes/train_policy.py`` (``episodes``, ``wall_s``, ``success_rate``,
    ``ci_low``, ``ci_high`` as fractions; ``eval_episodes`` optional).
    """
    if not rows:
        raise ValueError("rows is empty: nothing to plot")
    fig = _figure(10.0, 4.0)
    axes = fig.subplots(1, 2, sharey=True)
    counts = sorted({int(row["eval_episodes"]) for row in rows if row.get("eval_episodes")})
    if not counts:
        line = "greedy success rate"
    elif len(counts) == 1:
        line = f"greedy success rate ({counts[0]} episodes per point)"
    else:  # e.g. 20 per periodic evaluation, 100 for the final one
        line = f"greedy success rate ({' or '.join(map(str, counts))} episodes per point)"
    pct = lambda key: [100.0 * float(r[key]) for r in rows]  # noqa: E731
    for ax, key, label in ((axes[0], "episodes", "training episodes"), (axes[1], "wall_s", "wall-clock time (min)")):
        xs = [float(r[key]) / (60.0 if key == "wall_s" else 1.0) for r in rows]
        ax.fill_between(xs, pct("ci_low"), pct("ci_high"), alpha=0.25, label="95 % Wilson interval")
        ax.plot(xs, pct("success_rate"), "o-", ms=3, label=line)
        ax.axhline(0.0, color="0.35", lw=0.9, zorder=0)
        ax.set_xlabel(label)
        ax.set_ylim(-5.0, 105.0)
        ax.grid(alpha=0.3)
    axes[0].set_title("against training episodes")
    axes[1].set_title("against wall-clock time")
    axes[0].set_ylabel("success rate (%)")
    axes[0].legend(loc="best")
    fig.suptitle(title or "Agent learning curve")
    _save(fig, path, ".png", dpi)
    return fig


def plot_decision(heightmap, q_map, candidates, values, chosen, path: str | Path, *, max_height: float | None = None,
                  num_rotations: int | None = None, is_pick: bool | None = None, title: str | None = None,
                  dpi: float = 100):
    """One decision of the agent: where it could act, what it expected, what it chose.

    Args:
        heightmap: ``[H, W]`` (or ``[1, H, W]``) metres, the state.
        q_map: ``[R, H, W]`` Q of the current primitive (the max over rotations is shown) or ``[H, W]``;
            None skips the Q panel (agents without a Q network).
        candidates: ``[N, 3]`` (row, col, rotation bin), the planner's proposals; None skips them.
        values: ``[N]`` each candidate's value V(f(s, a)) (needed with ``candidates``).
        chosen: ``[3]`` the action taken (ringed in red).
        max_height: top of the height colour scale (m); default: the map's maximum.
        num_rotations: R (default: ``q_map``'s first dimension, else 8).
        title: the title's start; the primitive and the chosen action are appended.

    Candidates are numbered by value (1 = highest) on the maps and in the values panel (its y axis spans
    the values only, so close values stay apart).
    """
    h = _array(heightmap, "heightmap", 2)
    q = None
    if q_map is not None:
        q = _array(q_map, "q_map")
        if q.ndim == 4 and q.shape[0] == 1:
            q = q[0]
        if q.ndim == 3:
            num_rotations = num_rotations or q.shape[0]
            q = q.max(0)
        if q.shape != h.shape:
            raise ValueError(f"q_map must be [R, H, W] or [H, W] matching the heightmap {h.shape}, got {q.shape}")
    num_rotations = _bins(num_rotations)
    action = _array(chosen, "chosen", 1, np.int64)
    if action.shape != (3,):
        raise ValueError(f"chosen must be [3] (row, col, rotation bin), got shape {action.shape}")
    cands = vals = order = None
    if candidates is not None:
        cands = _actions(candidates, "candidates")
        if values is None:
            raise ValueError("values must be given with candidates ([N] values, one per candidate)")
        vals = _array(values, "values").reshape(-1)
        if vals.shape[0] != cands.shape[0]:
            raise ValueError(f"values must hold one value per candidate ({cands.shape[0]}), got {vals.shape[0]}")
        order = np.argsort(-vals, kind="stable")
    from matplotlib import patheffects

    panels = 1 + (q is not None) + (cands is not None)
    fig = _figure(4.5 * panels + 0.3, 4.4)
    fig.get_layout_engine().set(w_pad=0.25)  # room between a colour bar's label and the next panel's axis label
    axes = list(np.atleast_1d(fig.subplots(1, panels)))
    maps = [(axes.pop(0), "heightmap", h)]
    if q is not None:
        maps.append((axes.pop(0), "Q map (max over rotations)", q))
    kind = "" if is_pick is None else ("pick" if is_pick else "place")
    for ax, name, image in maps:
        if name == "heightmap":
            im = ax.imshow(image, cmap=HEIGHT_CMAP, norm=_height_norm(max_height or max(float(image.max()), 1e-3)),
                           interpolation="nearest")
            _heights_colourbar(fig, im, ax, shrink=0.8)
        else:
            im = ax.imshow(image, cmap=Q_CMAP, interpolation="nearest")
            fig.colorbar(im, ax=ax, label=f"Q of the {kind or 'current'} primitive (expected return)", shrink=0.8)
        ax.set_title(name)
        _pixel_axes(ax)
        handles = []
        if cands is not None:
            for rank, idx in enumerate(order, start=1):
                art = _draw_action(ax, cands[idx], num_rotations, "white", size=5, lw=1.0,
                                   label="candidate (number = rank by value)" if rank == 1 else None)
                ax.annotate(str(rank), (cands[idx, 1], cands[idx, 0]), xytext=(4, 4), textcoords="offset points",
                            color="white", fontsize=8, fontweight="bold", annotation_clip=False,
                            path_effects=[patheffects.withStroke(linewidth=2, foreground="black")])
                if rank == 1:
                    handles.append(art[1])
        handles.append(_draw_action(ax, action, num_rotations, CHOSEN_COLOUR, size=8, lw=2.0, label="chosen action")[1])
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=8)
    if cands is not None:
        ax = axes.pop(0)
        ranks, ranked = np.arange(1, len(order) + 1), vals[order]
        is_chosen = np.array([bool((cands[idx] == action).all()) for idx in order])
        ax.plot(ranks, ranked, "-", color="0.75", lw=1.0, zorder=1)
        ax.scatter(ranks[~is_chosen], ranked[~is_chosen], color="tab:blue", s=30, zorder=2, label="candidate")
        ax.scatter(ranks[is_chosen], ranked[is_chosen], color=CHOSEN_COLOUR, s=60, zorder=3, label="chosen")
        ax.set_xticks(ranks)
        ax.set_xlabel("candidate (rank by value)")
        ax.set_ylabel("value V(f(s, a)) (expected return)")
        ax.set_title(f"the {len(order)} candidates' values")
        ax.legend(loc="upper right", fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{title or 'Decision'}: {kind + ' ' if kind else ''}at ({action_text(action, num_rotations)})")
    _save(fig, path, ".png", dpi)
    return fig


def plot_episodes_gif(steps: Sequence[Mapping[str, Any]], path: str | Path, *, max_height: float,
                      num_rotations: int | None = None, fps: float = 1.0, title: str | None = None, dpi: float = 80):
    """A GIF, one frame per step: before (action drawn) | predicted next | real next heightmap.

    ``steps``: plain rows, one per step, in order, with ``heightmap`` and ``next_heightmap`` (``[H, W]``
    metres), ``action`` ``[3]``, and optionally ``predicted_heightmap`` (the world model's prediction for
    that action; without it the middle panel is left out), ``episode`` and ``step`` (ints, from 0),
    ``num_steps`` (the episode's length), ``is_pick`` (bool), ``reward`` (float), ``outcome`` (text shown on the episode's steps, e.g.
    ``"success"``). Written with matplotlib's PillowWriter (Pillow comes with matplotlib).
    """
    require_matplotlib()
    from matplotlib.animation import PillowWriter

    num_rotations = _bins(num_rotations)
    if not steps:
        raise ValueError("steps is empty: nothing to animate")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    for i, row in enumerate(steps):
        missing = [k for k in ("heightmap", "next_heightmap", "action") if k not in row]
        if missing:
            raise ValueError(f"steps[{i}] is missing {missing}; it has {sorted(row)}")
    with_prediction = all(row.get("predicted_heightmap") is not None for row in steps)
    names = ["before (the chosen action)"] + (["predicted next (world model)"] if with_prediction else []) + ["real next"]
    fig = _figure(3.2 * len(names) + 0.9, 3.9)
    axes = list(np.atleast_1d(fig.subplots(1, len(names))))
    blank = np.zeros_like(_array(steps[0]["heightmap"], "heightmap", 2))
    images = [ax.imshow(blank, cmap=HEIGHT_CMAP, norm=_height_norm(max_height), interpolation="nearest") for ax in axes]
    for ax in axes:
        _no_ticks(ax)
    _heights_colourbar(fig, images[0], axes, shrink=0.8)
    fig.supxlabel(f"{PIXELS_NOTE}; ring = action pixel, bar = fingers' closing direction", fontsize=7)
    head = fig.suptitle(title or "")
    drawn: list = []
    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"GIF path must end in .gif, got {str(path)!r}")
    from ldm_rl.run.outputs import atomic_path

    writer = PillowWriter(fps=fps)
    with atomic_path(path) as tmp:
        with writer.saving(fig, str(tmp), dpi):
            for row in steps:
                before = _array(row["heightmap"], "heightmap", 2)
                real = _array(row["next_heightmap"], "next_heightmap", 2)
                shown = [before] + ([_array(row["predicted_heightmap"], "predicted_heightmap", 2)] if with_prediction else []) + [real]
                for image, data in zip(images, shown):
                    image.set_data(data)
                for art in drawn:
                    art.remove()
                pick = row.get("is_pick")
                colour = PLACE_COLOUR if pick is False else PICK_COLOUR
                drawn = [a for ax in axes for a in _draw_action(ax, _array(row["action"], "action", 1, np.int64),
                                                                num_rotations, colour, size=6, lw=1.2)]
                for ax, name in zip(axes, names):
                    ax.set_title(name, fontsize=9)
                if with_prediction:
                    worst = 1000.0 * float(np.abs(shown[1] - real).max())
                    axes[1].set_title(f"{names[1]}\nlargest |error| vs real: {worst:.0f} mm", fontsize=9)
                kind = "" if pick is None else ("pick " if pick else "place ")
                parts = [title] if title else []
                if "episode" in row:
                    parts.append(f"episode {int(row['episode']) + 1}")
                if "step" in row:
                    of = f"/{int(row['num_steps'])}" if "num_steps" in row else ""
                    parts.append(f"step {int(row['step']) + 1}{of}")
                parts.append(f"{kind}at ({action_text(_array(row['action'], 'action', 1, np.int64), num_rotations)})")
                if "reward" in row:
                    parts.append(f"reward {float(row['reward']):g}")
                if row.get("outcome"):
                    parts.append(str(row["outcome"]))
                head.set_text(" · ".join(parts))
                writer.grab_frame()
    return fig
