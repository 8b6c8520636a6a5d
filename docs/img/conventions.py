"""Draw docs/img/conventions.png: PSD anodes, sensor axes, and the sign of the angles.

Run from the repository root: ``.venv/bin/python docs/img/conventions.py [OUT.png]``.
The geometry follows docs/model.md#hardware-conventions: Eq 1-2 put the
anodes X1, X2, Y1, Y2 at the corners (-,-), (+,+), (+,-), (-,+) of the
sensor frame, and the lens turns the image by 180 degrees, so the camera
frame is the chip frame turned about the optical axis.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, Rectangle  # noqa: E402

OUT = Path(__file__).with_name("conventions.png")
ANODES = {"X1 → vx1": (-1, -1), "X2 → vx2": (1, 1), "Y1 → vy1": (1, -1), "Y2 → vy2": (-1, 1)}


def arrow(ax, start, end, text, color="k", offset=(0.0, 0.0)):
    ax.add_patch(FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=14, color=color, lw=1.6))
    ax.text(end[0] + offset[0], end[1] + offset[1], text, color=color, ha="center", va="center", fontsize=10)


def front_view(ax):
    ax.add_patch(Rectangle((-4.5, -4.5), 9, 9, fc="#f2e6c9", ec="k"))
    for name, (sx, sy) in ANODES.items():
        ax.plot(4.5 * sx, 4.5 * sy, "s", ms=9, color="#b5651d")
        ax.text(5.3 * sx, 5.3 * sy, name, ha="center", va="center", fontsize=9)
    arrow(ax, (0, 0), (3.2, 0), "+x", "C0", (0.6, 0))
    arrow(ax, (0, 0), (0, 3.2), "+y", "C0", (0, 0.6))
    ax.text(0, -6.6, "front view: looking into the lens\n(x right, y up; Eq 1-2)", ha="center", fontsize=9)
    ax.set_title("PSD S5991-01 anodes and sensor axes", fontsize=10)
    ax.set_xlim(-7.5, 7.5)
    ax.set_ylim(-8, 7)


def side_view(ax):
    f, zs, ye = 6.0, 22.0, 5.0  # lens distance, emitter distance, emitter height (arbitrary units)
    ax.plot([0, 0], [-4.5, 4.5], color="#b5651d", lw=5)
    ax.text(-0.6, 4.9, "chip +y", ha="right", fontsize=9)
    ax.text(-0.6, -4.9, "chip −y", ha="right", fontsize=9)
    ax.plot([f, f], [-3, 3], color="C2", lw=2)
    ax.text(f, 3.5, "lens", ha="center", color="C2", fontsize=9)
    ax.axhline(0, color="0.6", lw=0.8, ls="--")
    ax.plot(zs, ye, "o", color="C3", ms=9)
    ax.text(zs, ye + 1.0, "emitter above the axis\nYc < 0, alpha_y < 0", ha="center", color="C3", fontsize=9)
    spot = -ye * f / (zs - f)
    ax.plot([zs, f, 0], [ye, 0, spot], color="C3", lw=1.2)
    ax.plot(0, spot, "o", color="C3", ms=6)
    ax.text(0.5, spot - 0.9, "spot on the −y half", color="C3", fontsize=9)
    arrow(ax, (f, -5.5), (f + 5, -5.5), "Zc", "C0", (0.9, 0))
    arrow(ax, (f, -5.5), (f, -8.0), "Yc", "C0", (0.9, 0))
    ax.set_title("side view: the lens inverts the image", fontsize=10)
    ax.set_xlim(-4, 27)
    ax.set_ylim(-9, 8.5)


def back_view(ax):
    ax.add_patch(Rectangle((-4.5, -4.5), 9, 9, fc="#eeeeee", ec="k"))
    arrow(ax, (0, 0), (3.2, 0), "Xc, +alpha_x", "C0", (0.2, 0.8))
    arrow(ax, (0, 0), (0, -3.2), "Yc, +alpha_y", "C0", (0.0, -0.8))
    ax.text(-3.2, 3.4, "chip +y up\nchip +x to the left", fontsize=9, va="top")
    ax.text(0, -6.6, "from behind the sensor, looking at the scene:\nemitter right → alpha_x > 0, below → alpha_y > 0",
            ha="center", fontsize=9)
    ax.set_title("camera frame and angle signs", fontsize=10)
    ax.set_xlim(-7.5, 7.5)
    ax.set_ylim(-8, 7)


def main(out: Path = OUT) -> Path:
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    front_view(axes[0])
    side_view(axes[1])
    back_view(axes[2])
    for ax in axes:
        ax.set_aspect("equal")
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    import sys

    print(main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT))
