"""Draw the capture guide's diagrams into docs/images/ (matplotlib, no data needed):
``python docs/make_figures.py``. The PNGs are committed; rerun this after changing a diagram."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

OUT = Path(__file__).resolve().parent / "images"


def _save(fig, name: str) -> None:
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / name, dpi=110, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {OUT / name}")


def camera_frame() -> None:
    """The colour camera's frame (x right, y down, z forward) and the LED offset, front and side views."""
    fig, (front, side) = plt.subplots(1, 2, figsize=(8.4, 3.8), layout="constrained")
    # front view: looking into the lens
    front.add_patch(plt.Rectangle((-6, -2.2), 12, 4.4, fill=False, lw=1.5))
    front.add_patch(plt.Circle((0, 0), 1.0, fill=False, lw=1.5))
    front.text(0, -1.5, "colour lens", ha="center", va="top", fontsize=8)
    front.add_patch(plt.Circle((3, -2), 0.45, color="gold", ec="k"))
    front.text(3.6, -2.6, "LED (3, -2, 0) cm", fontsize=8)
    front.annotate("", (3.2, 0), (0, 0), arrowprops=dict(arrowstyle="->", color="C3", lw=2))
    front.annotate("", (0, 3.2), (0, 0), arrowprops=dict(arrowstyle="->", color="C2", lw=2))
    front.text(3.3, 0.2, "x (right)", color="C3")
    front.text(0.2, 3.3, "y (down)", color="C2")
    front.set(xlim=(-7, 8), ylim=(5, -4), aspect="equal", title="front (facing the camera's view direction)",
              xlabel="x (cm)", ylabel="y (cm)")
    # side view: z forward towards the object
    side.add_patch(plt.Rectangle((-1.5, -2.2), 1.5, 4.4, fill=False, lw=1.5))
    side.add_patch(plt.Circle((0.0, -2), 0.45, color="gold", ec="k"))
    side.annotate("", (9, 0), (0, 0), arrowprops=dict(arrowstyle="->", color="C0", lw=2))
    side.annotate("", (0, 3.2), (0, 0), arrowprops=dict(arrowstyle="->", color="C2", lw=2))
    side.text(8.2, -0.5, "z (forward)", color="C0")
    side.text(0.2, 3.3, "y (down)", color="C2")
    side.add_patch(plt.Circle((14, 0.5), 2.5, color="0.8"))
    side.text(14, 3.6, "object, 0.5-1 m away", ha="center", fontsize=8)
    side.set(xlim=(-3, 18), ylim=(5, -4), aspect="equal", title="side", xlabel="z (cm, not to scale)",
             ylabel="y (cm)")
    fig.suptitle("Camera coordinates (metres in files): --led-offset 0.03 -0.02 0")
    _save(fig, "camera_frame.png")


def pose_convention() -> None:
    """Top view of a capture: frame 0 is the reference; T_i maps reference-camera coordinates into frame i's."""
    fig, ax = plt.subplots(figsize=(6.4, 4.6), layout="constrained")
    centre = np.array([0.0, 0.6])
    ax.add_patch(plt.Circle(centre, 0.1, color="0.8"))
    ax.text(*centre, "object", ha="center", va="center", fontsize=8)
    for i, angle in enumerate(np.radians([0, 15, 30, -15])):
        position = centre + 0.6 * np.array([np.sin(angle), -np.cos(angle)])
        forward = (centre - position) / np.linalg.norm(centre - position)
        right = np.array([forward[1], -forward[0]])
        corners = [position + 0.05 * right - 0.02 * forward, position - 0.05 * right - 0.02 * forward,
                   position + 0.06 * forward]
        ax.add_patch(plt.Polygon(corners, color="C0" if i == 0 else "C1", alpha=0.8))
        ax.annotate("", position + 0.12 * forward, position, arrowprops=dict(arrowstyle="->"))
        ax.text(*(position - 0.05 * forward - [0, 0.02 * (i % 2)]),
                "frame 0\n(reference)\n$T_0 = I$" if i == 0 else f"frame {i}", ha="center", va="top", fontsize=8)
    p0, p1 = centre + 0.6 * np.array([0, -1]), centre + 0.6 * np.array([np.sin(0.26), -np.cos(0.26)])
    ax.annotate("", p1 + [0.0, 0.16], p0 + [0.0, 0.16],
                arrowprops=dict(arrowstyle="->", color="C3", lw=1.5, connectionstyle="arc3,rad=-0.3"))
    ax.text(0.07, 0.3, "$T_1$ maps reference-camera\ncoordinates into frame 1's", color="C3", fontsize=9)
    ax.set(xlim=(-0.45, 0.55), ylim=(-0.22, 0.75), aspect="equal", xlabel="x (m)", ylabel="z (m)",
           title="Poses: $X_i = T_i X_0$ (4x4, metres), top view")
    _save(fig, "poses.png")


def grids() -> None:
    """Colour grid (H x W) and depth grid (H/SF x W/SF) over the same field of view; intrinsics."""
    fig, ax = plt.subplots(figsize=(6.4, 4.4), layout="constrained")
    W, H, SF = 16, 12, 4
    for u in range(W + 1):
        ax.plot([u, u], [0, H], color="0.85", lw=0.6)
    for v in range(H + 1):
        ax.plot([0, W], [v, v], color="0.85", lw=0.6)
    for u in range(0, W + 1, SF):
        ax.plot([u, u], [0, H], color="C0", lw=1.8)
    for v in range(0, H + 1, SF):
        ax.plot([0, W], [v, v], color="C0", lw=1.8)
    ax.plot(W / 2, H / 2, "+", color="C3", ms=14, mew=2)
    ax.text(W / 2 + 0.3, H / 2 - 0.3, "principal point $(c_x, c_y)$", color="C3")
    ax.annotate("", (W + 0.8, 0), (-0.2, 0), arrowprops=dict(arrowstyle="->"))
    ax.annotate("", (0, H + 0.8), (0, -0.2), arrowprops=dict(arrowstyle="->"))
    ax.text(W + 0.9, 0, "u (columns)", va="center")
    ax.text(0, H + 1.0, "v (rows)", ha="center", va="top")
    ax.text(W - 0.2, H - 0.3, "grey: colour pixels (W x H)\nblue: depth pixels (W/SF x H/SF), SF = 4",
            ha="right", va="bottom", fontsize=8, bbox=dict(fc="white", ec="0.7"))
    ax.set(xlim=(-1, W + 4), ylim=(H + 1.5, -1), aspect="equal",
           title="intrinsic.json: colour camera $f_x, f_y, c_x, c_y$ (pixels);\n"
                 "depth_intrinsic.json defaults to them scaled by 1/SF")
    ax.set_axis_off()
    _save(fig, "grids.png")


def depth_scale() -> None:
    """uint16 depth PNG value -> metres with capture.json's depth_scale; 0 = no measurement."""
    values = np.arange(0, 1200)
    fig, ax = plt.subplots(figsize=(6.4, 3.4), layout="constrained")
    for scale, label in ((1000, "depth_scale 1000 (mm, default)"), (4000, "depth_scale 4000 (0.25 mm units)")):
        ax.plot(values, values / scale, label=label)
    ax.plot([0], [0], "o", color="C3")
    ax.annotate("0 = no measurement", (0, 0), (150, 0.85), arrowprops=dict(arrowstyle="->", color="C3"), color="C3")
    ax.axhline(0.6, color="0.6", ls=":")
    ax.text(1190, 0.62, "0.6 m: value 600 at scale 1000", ha="right", fontsize=8)
    ax.set(xlabel="value in depth/000000.png (uint16)", ylabel="depth z (m)", ylim=(-0.05, 1.25),
           title="Depth PNGs: z = value / depth_scale")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    _save(fig, "depth_scale.png")


if __name__ == "__main__":
    camera_frame()
    pose_convention()
    grids()
    depth_scale()
