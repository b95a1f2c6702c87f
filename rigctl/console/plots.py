"""The console's figures, drawn with matplotlib's object API (no pyplot state, so the
service's threads can draw at once) into PNG bytes."""

from __future__ import annotations

import datetime as dt
import io

import numpy as np
from matplotlib.dates import AutoDateLocator, ConciseDateFormatter
from matplotlib.figure import Figure

from rigctl.console.compare import ArmDifference, ProjectionDifference
from rigctl.console.history import Series

STYLE = {  # decision -> (colour, marker, filled)
    "accepted": ("#1a7f37", "o", True),
    "rejected": ("#6e7781", "X", True),
    "drift": ("#c62828", "^", True),
    "pending": ("#b26a00", "s", False),
}


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


SINGLE_POINT_PAD = dt.timedelta(hours=1)
MIN_PAD = dt.timedelta(seconds=5)


def _time_axis(ax, times: list[dt.datetime]) -> None:
    """Dates that read well at any span: an hour either side of a single time (not the
    years matplotlib picks around one point), else the points' own span with a margin of
    8 % (at least 5 s), so that runs minutes apart spread over the axis instead of
    crowding into the middle of an hour-wide one."""
    lo, hi = min(times), max(times)
    pad = SINGLE_POINT_PAD if hi == lo else max((hi - lo) * 0.08, MIN_PAD)
    ax.set_xlim(lo - pad, hi + pad)
    locator = AutoDateLocator(minticks=3, maxticks=6)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(ConciseDateFormatter(locator))


def history_png(title: str, all_series: list[Series]) -> bytes:
    """One panel per quantity: values with 1-sigma error bars over time, coloured and
    shaped by decision, with the drift band around the last accepted value."""
    shown = [s for s in all_series if s.values]
    fig = Figure(figsize=(10, 2.6 * max(1, (len(shown) + 1) // 2)), layout="constrained")
    if not shown:
        fig.text(0.5, 0.5, f"{title}: no finished calibrations yet", ha="center")
        return _png(fig)
    axes = fig.subplots((len(shown) + 1) // 2, 2, squeeze=False).ravel()
    for ax, s in zip(axes, shown, strict=False):
        if s.band is not None:
            ax.axhspan(s.accepted - s.band, s.accepted + s.band, color="#1a7f37", alpha=0.08,
                       label="drift band")
            ax.axhline(s.accepted, color="#1a7f37", lw=0.6, ls="--")
        ax.plot(s.times, s.values, color="#999", lw=0.7, zorder=1)
        for decision, (colour, marker, filled) in STYLE.items():
            idx = [i for i, d in enumerate(s.decisions) if d == decision]
            if not idx:
                continue
            yerr = [s.sigmas[i] or 0.0 for i in idx]
            ax.errorbar([s.times[i] for i in idx], [s.values[i] for i in idx],
                        yerr=yerr, fmt=marker, color=colour, ms=6, capsize=3,
                        mfc=colour if filled else "white", label=decision, zorder=3)
        ax.set_title(f"{s.quantity.label} ({s.quantity.unit})", fontsize=10)
        ax.ticklabel_format(axis="y", useOffset=False)
        _time_axis(ax, s.times)
        ax.legend(fontsize=7, loc="best")
    for ax in axes[len(shown):]:
        ax.set_visible(False)
    fig.suptitle(title, fontsize=11)
    return _png(fig)


HEAT_MAP_FLOOR_PX = 0.1


def heat_map_max_px(pd: ProjectionDifference) -> float:
    """The colour scale's top: the largest difference, but never under a tenth of a pixel,
    so that two equal calibrations (a difference of 1e-7 px) show as one flat colour
    rather than as a pattern of rounding errors stretched over the whole scale."""
    return max(float(pd.diff_px.max()), HEAT_MAP_FLOOR_PX)


def projection_difference_png(pd: ProjectionDifference, width: int, height: int) -> bytes:
    """Heat maps of the projection difference (px) and of the difference over its
    1-sigma, across the image."""
    panels = 2 if pd.sigma_px is not None else 1
    fig = Figure(figsize=(5.2 * panels, 3.4), layout="constrained")
    axes = fig.subplots(1, panels, squeeze=False).ravel()
    extent = (0, width, height, 0)
    im = axes[0].imshow(pd.diff_px, extent=extent, cmap="viridis", aspect="equal",
                        vmin=0, vmax=heat_map_max_px(pd))
    fig.colorbar(im, ax=axes[0], shrink=0.85, label="px")
    axes[0].set_title("projection difference (px)", fontsize=10)
    if panels == 2:
        z = pd.z
        im = axes[1].imshow(z, extent=extent, cmap="RdYlGn_r", vmin=0,
                            vmax=max(6.0, float(z.max())), aspect="equal")
        if z.max() > 3 > z.min():
            axes[1].contour(pd.u, pd.v, z, levels=[3.0], colors="k", linewidths=0.8)
        fig.colorbar(im, ax=axes[1], shrink=0.85, label="difference / 1-sigma")
        axes[1].set_title("difference over its uncertainty (3 = resolved)", fontsize=10)
    for ax in axes:
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    return _png(fig)


def arm_difference_png(ad: ArmDifference) -> bytes:
    """The camera position difference at each configuration (sorted), against 1 and 3
    sigma of the difference."""
    order = np.argsort(ad.diff_mm)
    x = np.arange(len(order))
    fig = Figure(figsize=(8, 3.2), layout="constrained")
    ax = fig.subplots()
    ax.plot(x, ad.diff_mm[order], "o", ms=4, color="#0b5cad", label="difference")
    if ad.sigma_mm is not None:
        ax.plot(x, ad.sigma_mm[order], "-", color="#b26a00", lw=1, label="1 sigma")
        ax.plot(x, 3 * ad.sigma_mm[order], "--", color="#c62828", lw=1, label="3 sigma")
    ax.set_xlabel("configuration of this run (sorted by difference)")
    ax.set_ylabel("camera position difference (mm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.set_title("camera position, this model vs the accepted one", fontsize=10)
    return _png(fig)
