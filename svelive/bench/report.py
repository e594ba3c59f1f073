"""Writing benchmark results: results.json, results.csv, the speed/accuracy chart, a Markdown table.

Files are written to a temporary name and renamed, so a reader never sees half
a file. matplotlib (the optional extra ``bench``) is imported only to draw.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from svelive.core.atomic import write_bytes_atomic
from svelive.core.errors import SveliveError

REALTIME_MS = 33.0  # 30 frames per second
BUDGET_MS = 25.0  # the reconstruction's share of a frame


def write_json(path: Path, data: object) -> None:
    write_bytes_atomic(path, (json.dumps(data, indent=1) + "\n").encode())


def write_csv(path: Path, rows: list[dict[str, object]]) -> None:
    """One line per row, columns in the rows' key order."""
    if not rows:
        raise SveliveError("no benchmark results to write")
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: f"{v:.4g}" if isinstance(v, float) else v for k, v in row.items()})
    write_bytes_atomic(path, text.getvalue().encode())


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise SveliveError("the chart needs matplotlib: pip install 'svelive[bench]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> None:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    write_bytes_atomic(path, buffer.getvalue())


def plot_speed_accuracy(summary: list[dict[str, object]], path: Path, default: str | None = None) -> None:
    """Mean PU21-PSNR against median time per frame (log x), Pareto front, 33 ms and 25 ms marks, bracketing line."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    pts = sorted(((s["ms_per_frame"], s["pu21_psnr"], s["method"], s["pareto"]) for s in summary))
    for t, a, name, on in pts:
        ax.scatter([t], [a], s=60 if name == default else 36, marker="*" if name == default else "o",
                   color="tab:red" if on else "tab:blue", zorder=3)
        ax.annotate(name + (" (default)" if name == default else ""), (t, a), textcoords="offset points",
                    xytext=(6, 4), fontsize=8)
    front = [(t, a) for t, a, _, on in pts if on]
    ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="tab:red", lw=1,
            label="Pareto front")
    ref = float(sum(s["reference_pu21_psnr"] for s in summary) / len(summary))
    ax.axhline(ref, color="tab:green", ls="--", lw=1, label=f"bracketing reference ({ref:.1f} dB)")
    ax.axvline(REALTIME_MS, color="grey", ls=":", lw=1, label="real time, 33 ms")
    ax.axvline(BUDGET_MS, color="black", ls=":", lw=1, label="budget, 25 ms")
    log_x(ax, (5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000))
    ax.set_xlabel("time per 1920x1200 frame, one thread (ms, median)")
    ax.set_ylabel("PU21-PSNR (dB), mean over images, patterns, noise levels")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    save_figure(fig, path)
    plt.close(fig)


def log_x(ax, ticks: tuple[float, ...]) -> None:
    """A log x axis labelled with the plain numbers of ``ticks`` that fall inside it."""
    from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

    ax.set_xscale("log")
    lo, hi = ax.get_xlim()
    ax.xaxis.set_major_locator(FixedLocator([t for t in ticks if lo <= t <= hi]))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())


def plot_live(results: dict[str, object], path: Path) -> None:
    """The live chart (svelive.bench.live): mean PU21-PSNR against frames per second on this machine (log x), one
    marker per ladder step, a line per kind (mono, colour) in ladder order, the 30 fps mark."""
    plt = _pyplot()
    rows, config = results["rows"], results["config"]
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    steps = list(dict.fromkeys(r["step"] for r in rows))
    markers = "o^sDvP*X"
    for i, kind in enumerate(dict.fromkeys(r["kind"] for r in rows)):
        mine = [r for r in rows if r["kind"] == kind]
        colour = f"C{i}"
        ax.plot([r["fps"] for r in mine], [r["pu21"] for r in mine], color=colour, lw=1, ls="--", alpha=0.6,
                label=f"{kind} ({mine[0]['camera']})")
        for r in mine:
            ax.scatter([r["fps"]], [r["pu21"]], marker=markers[steps.index(r["step"]) % len(markers)], s=48,
                       color=colour, zorder=3)
            ax.annotate(r["step"], (r["fps"], r["pu21"]), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.axvline(30.0, color="grey", ls=":", lw=1, label="real time, 30 fps")
    log_x(ax, (1, 2, 5, 10, 20, 30, 50, 100, 200, 500, 1000, 2000))
    rows_px, cols_px = config["timing_size"]
    load = results["machine"].get("load_average_at_start")
    ax.set_xlabel(f"frames per second, {cols_px}x{rows_px}, {config['workers']} workers, this machine"
                  + ("" if load is None else f" (load {load[0]:.1f})"))
    ax.set_ylabel(f"PU21-PSNR (dB) after {config['frames']} frames of a still scene, mean bright/dim")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    save_figure(fig, path)
    plt.close(fig)


def plot_curves(sweeps: list[dict[str, object]], path: Path) -> None:
    """One panel per stability sweep: error against difficulty, one line per method."""
    plt = _pyplot()
    n = len(sweeps)
    cols = 3
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    for ax, sweep in zip(axes.ravel(), sweeps):
        layouts = list(dict.fromkeys(label.split(" ", 1)[-1] for label in sweep["errors"]))
        for method, errors in sweep["errors"].items():
            style = {}
            if sweep["name"].startswith("colour"):  # "<mode> <layout>": a colour per layout, split dashed
                mode, layout = method.split(" ", 1)
                style = {"color": f"C{layouts.index(layout)}", "ls": "--" if mode == "split" else "-"}
            ax.plot(sweep["difficulty"], errors, marker=".", label=method, **style)
        if sweep["name"].startswith(("colour", "stream")):  # series other than the first panel's methods
            ax.legend(fontsize=6)
        ax.set_title(sweep["title"], fontsize=9)
        ax.set_xlabel(sweep["axis"], fontsize=8)
        ax.set_ylabel(sweep["error"], fontsize=8)
        if sweep.get("log_y"):
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    axes.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def markdown_table(summary: list[dict[str, object]]) -> str:
    """The summary as a Markdown table, fastest first."""
    head = ("| method | ms / frame | PU21-PSNR | bright | dim | log-PSNR | mu-law PSNR | p99 error (stops)"
            " | below bracketing (dB) | Pareto |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---|\n")
    lines = []
    for s in sorted(summary, key=lambda s: s["ms_per_frame"]):
        lines.append(f"| {s['method']} | {s['ms_per_frame']:.1f} | {s['pu21_psnr']:.2f} | {_f(s['pu21_psnr_bright'])} |"
                     f" {_f(s['pu21_psnr_dim'])} | {s['log_psnr']:.2f} | {s['mu_law_psnr']:.2f} |"
                     f" {s['error_stops_p99']:.3f} | {s['below_reference_db']:.2f} | {'yes' if s['pareto'] else ''} |")
    return head + "\n".join(lines) + "\n"


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_choice_map(truth: np.ndarray, share: np.ndarray, path: Path, title: str) -> None:
    """Scene (log2 radiance) beside the adaptive method's per-pixel weight of the pixel's own reading."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.4))
    shown = axes[0].imshow(np.log2(np.maximum(truth, 1e-3)), cmap="gray")
    axes[0].set_title("scene, log2 radiance", fontsize=9)
    fig.colorbar(shown, ax=axes[0], fraction=0.046)
    shown = axes[1].imshow(share, cmap="viridis", vmin=0, vmax=1)
    axes[1].set_title("own reading's weight (1: full resolution, 0: neighbours)", fontsize=9)
    fig.colorbar(shown, ax=axes[1], fraction=0.046)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path)
    plt.close(fig)


def plot_colour(results: dict[str, object], path: Path) -> None:
    """Colour benchmark: PU21-PSNR of luminance and mean CIEDE2000 (p99 as a tick) per layout and noise level,
    one bar per setting (means over the images)."""
    plt = _pyplot()
    rows = results["rows"]
    groups = list(dict.fromkeys((r["layout"], r["noise"]) for r in rows))
    labels = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.6))
    width = 0.8 / len(labels)
    x = np.arange(len(groups))

    def mean(label: str, group: tuple[str, str], metric: str) -> float:
        return float(np.mean([r[metric] for r in rows if r["method"] == label and (r["layout"], r["noise"]) == group]))

    methods = list(dict.fromkeys(label.partition(" ")[2] for label in labels))  # "joint weighted" -> "weighted"
    for i, label in enumerate(labels):
        offset = x - 0.4 + width * (i + 0.5)
        style = {"hatch": "//" if label.startswith("split") else None, "edgecolor": "white",
                 "color": f"C{methods.index(label.partition(' ')[2])}"}  # one colour per method, split hatched
        axes[0].bar(offset, [mean(label, g, "pu21_y") for g in groups], width, label=label, **style)
        axes[1].bar(offset, [mean(label, g, "de2000_mean") for g in groups], width, label=label, **style)
        axes[1].scatter(offset, [mean(label, g, "de2000_p99") for g in groups], marker="_", s=80, color="black",
                        zorder=3, label="p99" if i == 0 else None)
    for ax, title in zip(axes, ("PU21-PSNR of luminance (dB, higher is better)",
                                "CIEDE2000 of the sRGB rendering (mean bars, p99 ticks; lower is better)")):
        ax.set_xticks(x)
        ax.set_xticklabels([f"{layout}\n{noise}" for layout, noise in groups], fontsize=6.5)
        ax.set_title(title, fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
        ax.tick_params(labelsize=7)
    y = [mean(label, g, "pu21_y") for label in labels for g in groups]
    axes[0].set_ylim(min(y) - 3, max(y) + 1)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[1].legend(fontsize=7)
    n = len(results["images"])
    fig.suptitle(f"colour SVE: joint reconstruction against the split baseline, mean over {n} RGB images", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def plot_colour_edges(crops: list[dict[str, object]], path: Path) -> None:
    """A grid of rendered edge crops (svelive.bench.stability.colour_edge_crops): one row per layout,
    for each contrast one column per image (truth, then each setting)."""
    plt = _pyplot()
    labels = list(crops[0]["images"])
    layouts = list(dict.fromkeys(c["layout"] for c in crops))
    contrasts = list(dict.fromkeys(c["contrast"] for c in crops))
    cols = len(contrasts) * len(labels)
    fig, axes = plt.subplots(len(layouts), cols, figsize=(1.6 * cols, 1.7 * len(layouts)), squeeze=False)
    for crop in crops:
        row = layouts.index(crop["layout"])
        for j, label in enumerate(labels):
            ax = axes[row, contrasts.index(crop["contrast"]) * len(labels) + j]
            ax.imshow(crop["images"][label], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"{label}, {crop['contrast']:g} stops", fontsize=8)
        axes[row, 0].set_ylabel(crop["layout"], fontsize=8)
    fig.suptitle("slanted black/white edge (centre 36x36 px, white-balanced, fixed rendering)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def plot_grid(results: dict[str, object], path: Path) -> None:
    """The guard grid as heat maps of the default's margin over the best rival (dB), one per metric and true sensor.

    Rows: image x pattern; columns: light level x noise model given. Cells below
    the tolerance are outlined.
    """
    plt = _pyplot()
    rows, tolerance = results["rows"], results["config"]["tolerance_db"]
    sensors = list(dict.fromkeys(r["sensor"] for r in rows))
    lines = list(dict.fromkeys((r["image"], r["pattern"]) for r in rows))
    columns = list(dict.fromkeys((r["stops"], r["model"]) for r in rows))
    size = (2 + 0.44 * len(columns), 1.2 + 0.2 * len(lines) * len(sensors))
    fig, axes = plt.subplots(len(sensors), 2, figsize=size, squeeze=False)
    for i, sensor in enumerate(sensors):
        for j, metric in enumerate(("pu21", "log")):
            margin = np.full((len(lines), len(columns)), np.nan)
            for r in rows:
                if r["sensor"] == sensor:
                    margin[lines.index((r["image"], r["pattern"])), columns.index((r["stops"], r["model"]))] = \
                        r[f"margin_{metric}"]
            ax = axes[i, j]
            shown = ax.imshow(np.clip(margin, -3, 3), cmap="RdBu", vmin=-3, vmax=3, aspect="auto",
                              interpolation="nearest")
            for y, x in zip(*np.nonzero(margin < -tolerance)):
                ax.add_patch(plt.Rectangle((x - 0.5, y - 0.5), 1, 1, fill=False, ec="black", lw=0.8))
            ax.set_yticks(range(len(lines)), [f"{a} {b}" for a, b in lines], fontsize=5)
            ax.set_xticks(range(len(columns)), [f"{s:g} {m}" for s, m in columns], fontsize=5, rotation=90)
            ax.set_title(f"{'PU21-PSNR' if metric == 'pu21' else 'log-PSNR'} margin of the default over "
                         f"max(aggregate, weighted), true sensor {sensor} (dB; outlined < -{tolerance:g})", fontsize=7)
            fig.colorbar(shown, ax=ax, fraction=0.03)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
