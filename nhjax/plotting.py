"""Matplotlib figures for Iwai's falling cat (``nhjax.scenes.FallingCat``).

``draw_cat`` draws the two jointed cylinders at one configuration,
``somersault_figure`` a grid of such snapshots along a trajectory (like Fig. 1
of Iwai 2002) and ``shape_path_figure`` the shape loop, the turn psi(t), the
torques and the shape variables. Lengths are in m, angles in rad, times in s,
torques in N m. matplotlib is imported inside the functions, so that
``import nhjax`` does not need it.

matplotlib's 3-D axes have no depth buffer: they paint faces back to front,
sorted by depth within one artist and artist by artist. The cylinders are
therefore drawn as a single ``Poly3DCollection`` of flat-shaded faces (not with
``plot_surface``, whose separate surfaces would be painted over each other in
the wrong order), back faces are culled, and the ends that interpenetrate at
the joint are mitred away.
"""

from __future__ import annotations

import numpy as np

__all__ = ["draw_cat", "shape_path_figure", "somersault_figure"]

_ELEV, _AZIM = 25.0, 70.0  # default camera [deg]; e2 (the turning axis) is vertical


def _eye(elev, azim):
    """Unit vector from the scene towards the camera (matplotlib's convention, e2 vertical)."""
    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])


def _closed_ring(section):
    """Closed polygon (m+1, 3) in the body (x, z) plane from its vertices ``section`` (m, 2)."""
    return np.insert(np.append(section, section[:1], 0), 1, 0.0, axis=1)


def _extrude(section, length, n_len):
    """Quads (k, 4, 3) and outward normals (k, 3) of the polygon ``section`` (m, 2) of the body
    (x, z) plane, counter-clockwise, swept along body e2 over |y| <= length/2 in ``n_len``
    slices, finer towards the ends, where the cylinders meet."""
    ring = _closed_ring(section)
    ys = np.outer(-length / 2 * np.cos(np.linspace(0, np.pi, n_len + 1)), [0.0, 1.0, 0.0])[:, None]
    lo, hi = ring + ys[:-1], ring + ys[1:]
    quads = np.stack([lo[:, :-1], lo[:, 1:], hi[:, 1:], hi[:, :-1]], 2).reshape(-1, 4, 3)
    d = np.diff(ring, axis=0)
    normals = np.stack([d[:, 2], 0 * d[:, 0], -d[:, 0]], -1) / np.hypot(d[:, 0], d[:, 2])[:, None]
    return quads, np.tile(normals, (n_len, 1))


def _cylinder_faces(radius, length, n_theta, n_len=12, n_rings=4):
    """Faces (k, 4, 3), outward normals (k, 3) and a mask of the marker-rod faces of one
    cylinder in its body frame: the side, both end caps, and a rod of square section
    (side 0.14 radius) resting on the surface along the body +x side."""
    a = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    circle = radius * np.stack([np.cos(a), np.sin(a)], -1)
    side, side_n = _extrude(circle, length, n_len)
    rings = np.linspace(0, 1, n_rings + 1)[:, None, None] * _closed_ring(circle)
    disc = np.stack([rings[:-1, :-1], rings[1:, :-1], rings[1:, 1:], rings[:-1, 1:]], 2).reshape(-1, 4, 3)
    caps = [disc + [0.0, s * length / 2, 0.0] for s in (-1.0, 1.0)]
    caps_n = [np.broadcast_to([0.0, s, 0.0], (len(disc), 3)) for s in (-1.0, 1.0)]
    w = 0.07 * radius
    rod_section = np.array([[radius, -w], [radius + 2 * w, -w], [radius + 2 * w, w], [radius, w]])
    rod, rod_n = _extrude(rod_section, length, n_len)
    faces = np.concatenate([side, *caps, rod])
    normals = np.concatenate([side_n, *caps_n, rod_n])
    return faces, normals, np.arange(len(faces)) >= len(faces) - len(rod)


def _mitre(points, joint, d_own, d_other, reach):
    """Trim a cylinder at the joint's mirror plane (the plane swapping the unit directions
    ``d_own`` and ``d_other`` from the joint to the centres): points beyond it slide along
    the axis onto it, but not past the far end, at distance ``reach`` from the joint. For
    cylinders jointed end to end the trimmed parts lie inside the other cylinder, so this
    draws their union (approximately once the cat is folded so far, within about
    2 atan(radius/length) of closing, that the far ends overlap too). Returns the points
    and a mask of those that were beyond."""
    m = d_own - d_other
    h = (points - joint) @ m
    beyond = h < 0
    if m @ d_own > 1e-9:
        slide = np.minimum(np.maximum(-h, 0) / (m @ d_own), reach - (points - joint) @ d_own)
        points = points + np.maximum(slide, 0)[..., None] * d_own
    return points, beyond


def draw_cat(
    ax, cat, q, *, colors=("tab:orange", "tab:blue"), alpha=1.0, n_theta=24, elev=_ELEV, azim=_AZIM
):
    """Draw the cat at q = (theta, chi, psi) [rad] on a 3-D axis ``ax``; returns ``ax``.

    Each cylinder (radius ``cat.radius``, length ``cat.length`` [m], placed by
    ``cat.poses``) is a shaded solid with end caps, in ``colors[i]`` with
    opacity ``alpha`` (below 1 the facet seams show faintly), divided into
    ``n_theta`` facets around its axis. A black marker rod runs along each
    cylinder's body +x side so that its spin about its own axis shows; dotted
    lines show the rods where they are hidden. The cylinders are mitred where
    they interpenetrate at the joint. e2, the axis of the overall turn
    psi, is a thin dashed line through the centre of mass. The axis limits are a
    cube fixed by ``cat.l``, ``cat.length`` and ``cat.radius`` (equal aspect,
    comparable between snapshots); the camera (orthographic, e2 vertical) looks
    from elevation ``elev`` and azimuth ``azim`` [deg].
    """
    from matplotlib.colors import to_rgb
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    radius, length, l = float(cat.radius), float(cat.length), float(cat.l)  # noqa: E741
    q = np.asarray(q, float)
    Rs, rs = (np.asarray(v) for v in cat.poses(q))
    joint = np.asarray(cat.joint(q))
    faces, normals, is_rod = _cylinder_faces(radius, length, n_theta)
    rod_axis = np.array([[1.07 * radius, -length / 2, 0.0], [1.07 * radius, length / 2, 0.0]])
    eye = _eye(elev, azim)
    light = eye + np.array([0.0, 0.8, 0.0]) + 0.4 * np.cross([0.0, 1.0, 0.0], eye)
    light /= np.linalg.norm(light)
    polys, rgba, rod_lines = [], [], []
    for i, (R, r, color) in enumerate(zip(Rs, rs, colors)):
        n = normals @ R.T
        d_own, d_other = (rs[i] - joint) / l, (rs[1 - i] - joint) / l
        world, beyond = _mitre(faces @ R.T + r, joint, d_own, d_other, l + length / 2)
        # painter's algorithm: mitre the interpenetrating ends, cull the back faces
        keep = (n @ eye > 0) & ~beyond.all(1)
        shade = 0.35 + 0.65 * np.clip(n[keep] @ light, 0, 1)
        base = np.where(is_rod[keep, None], 0.08, np.array(to_rgb(color)))
        rgba.append(np.column_stack([base * shade[:, None], np.full(len(shade), alpha)]))
        polys.append(world[keep])
        rod_lines.append(_mitre(rod_axis @ R.T + r, joint, d_own, d_other, l + length / 2)[0])
    rgba = np.concatenate(rgba)
    ax.add_collection3d(
        Poly3DCollection(np.concatenate(polys), facecolors=rgba, edgecolors=rgba, linewidths=0.3, zorder=1)
    )
    # "x-ray" lines over the solids: the e2 axis, and the rods (dotted where hidden)
    lim = l + np.hypot(length / 2, radius)
    ax.plot([0, 0], [-lim, lim], [0, 0], "--", color="0.35", lw=0.8, zorder=2)
    for line in rod_lines:
        ax.plot(*line.T, ":", color="k", lw=1.0, zorder=2)
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim))
    ax.set_box_aspect((1, 1, 1), zoom=1.5)
    ax.computed_zorder = False
    ax.view_init(elev=elev, azim=azim, vertical_axis="y")
    ax.set_proj_type("ortho")
    ax.set_axis_off()
    return ax


def somersault_figure(cat, traj, n_snapshots=8, path=None, *, elev=_ELEV, azim=_AZIM):
    """Snapshots of the cat at ``n_snapshots`` equally spaced times of ``traj``.

    ``traj`` is a ``Trajectory`` of ``FallingCat`` (states theta, chi, psi, ...
    [rad, rad/s]); the configurations between saved times are interpolated
    linearly. Panels are laid out in one row (up to 5) or two rows, titled with
    the time [s] and psi [rad]; the camera ``elev``, ``azim`` [deg] is that of
    ``draw_cat``, whose default looks at the cat side-on from slightly above
    e2, so that the bend plane visibly swings round e2 and the markers show
    first the front and, after the half turn, the back of the cat. Returns the
    ``Figure``; saves it as PNG to ``path`` (dpi 120) if given.
    """
    from matplotlib.figure import Figure

    ts, xs = np.asarray(traj.ts), np.asarray(traj.xs)
    times = np.linspace(ts[0], ts[-1], n_snapshots)
    qs = np.stack([np.interp(times, ts, xs[:, k]) for k in range(3)], -1)
    ncols = n_snapshots if n_snapshots <= 5 else -(-n_snapshots // 2)
    nrows = -(-n_snapshots // ncols)
    fig = Figure(figsize=(2.6 * ncols, 2.8 * nrows), layout="constrained")
    for k, (t, q) in enumerate(zip(times, qs)):
        ax = fig.add_subplot(nrows, ncols, k + 1, projection="3d")
        draw_cat(ax, cat, q, elev=elev, azim=azim)
        ax.set_title(rf"$t$ = {t:.2f} s, $\psi$ = {q[2]:.2f}", fontsize=10)
    turn = qs[-1, 2] - qs[0, 2]
    fig.suptitle(rf"Falling cat at zero angular momentum: $\psi$ turns by {turn:.2f} rad")
    caption = (
        r"dashed: $e_2$, the axis of the overall rotation $\psi$;   black rods: markers on the "
        r"cylinders' body $+e_1$ sides (dotted where hidden)"
    )
    fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=9, color="0.3")
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def shape_path_figure(cat, traj, path=None, closed_form_turn=None):
    """Shape loop and time histories of a ``FallingCat`` trajectory, 2x2 panels.

    (a) the path in shape space, drawn in polar coordinates (radius theta,
    angle chi [rad]; the origin is the straight cat); (b) psi(t) [rad], with a
    dashed line at ``closed_form_turn`` [rad] if given; (c) the torques
    ``traj.us`` [N m] (if any); (d) theta(t) and chi(t) [rad]. ``cat`` is
    unused by the panels but kept for a uniform signature. Returns the
    ``Figure``; saves it as PNG to ``path`` (dpi 120) if given.
    """
    from matplotlib.figure import Figure

    ts, xs = np.asarray(traj.ts), np.asarray(traj.xs)
    theta, chi, psi = xs[:, 0], xs[:, 1], xs[:, 2]
    fig = Figure(figsize=(10, 7.5), layout="constrained")
    ax = fig.add_subplot(2, 2, 1, projection="polar")
    ax.plot(chi, theta, color="tab:purple", lw=1.5)
    arc = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(theta * np.exp(1j * chi))))])
    for k in np.minimum(np.searchsorted(arc, np.linspace(0.1, 0.9, 5) * arc[-1]), len(ts) - 2):
        arrow = dict(arrowstyle="-|>", color="tab:purple", mutation_scale=15, shrinkA=0, shrinkB=0)
        ax.annotate("", xy=(chi[k + 1], theta[k + 1]), xytext=(chi[k], theta[k]), arrowprops=arrow)
    ax.plot(chi[0], theta[0], "o", color="k", label="start")
    ax.plot(chi[-1], theta[-1], "x", color="tab:red", ms=9, mew=2, label="end")
    ax.set_rmax(1.15 * theta.max())
    ax.set_rlabel_position(100)
    ax.tick_params(axis="y", labelsize=8)
    for label in ax.get_yticklabels():
        label.set_bbox(dict(facecolor="white", edgecolor="none", alpha=0.8, pad=0.5))
    ax.set_xticks(
        np.arange(8) * np.pi / 4,
        ["0", r"$\pi/4$", r"$\pi/2$", r"$3\pi/4$", r"$\pm\pi$", r"$-3\pi/4$", r"$-\pi/2$", r"$-\pi/4$"],
    )
    ax.legend(loc="lower left", bbox_to_anchor=(-0.2, -0.1), fontsize=8)
    ax.set_title("(a) shape path: radius $\\theta$, angle $\\chi$ [rad]\n(origin: the straight cat)", size=10)
    ax = fig.add_subplot(2, 2, 2)
    ax.plot(ts, psi, color="tab:green", label=r"$\psi$")
    if closed_form_turn is not None:
        turn = float(closed_form_turn)
        ax.axhline(turn, ls="--", color="0.3", label=f"closed form {turn:.4f}")
    ax.set(xlabel="t [s]", ylabel=r"$\psi$ [rad]", title=r"(b) overall rotation $\psi$ about $e_2$")
    ax.legend()
    ax = fig.add_subplot(2, 2, 3)
    if traj.us is not None:
        us = np.asarray(traj.us)
        ax.plot(ts, us[:, 0], label=r"$u_1$ (on $\theta$)")
        ax.plot(ts, us[:, 1], label=r"$u_2$ (on $\chi$)")
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no control", transform=ax.transAxes, ha="center", color="0.4")
    ax.set(xlabel="t [s]", ylabel="torque [N m]", title="(c) joint torques")
    ax = fig.add_subplot(2, 2, 4)
    ax.plot(ts, theta, label=r"$\theta$ (half bend)")
    ax.plot(ts, chi, label=r"$\chi$ (twist)")
    ax.set(xlabel="t [s]", ylabel="angle [rad]", title="(d) shape variables")
    ax.legend()
    for ax in fig.axes[1:]:
        ax.grid(alpha=0.3)
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def optimal_somersault_figure(ts, qs, us, ps=None, us_check=None, turn=None, path=None):
    """An optimal somersault at a glance, 2x2 panels.

    ``ts`` (N,) [s]; ``qs`` (N, 3) Iwai's (theta, chi, psi) [rad]; ``us`` (N, 2) the
    optimal inputs (w1', w2') [rad/s] of the smooth coordinates w = theta (cos chi,
    sin chi); ``ps`` (N, 3) the costates (p_w1, p_w2, p_phi) [J s / rad] of the
    Pontryagin extremal (or None); ``us_check`` (N, 2) a second solution's inputs
    drawn dashed (e.g. the direct optimum against the indirect one); ``turn`` the
    target of psi [rad]. Panels: (a) the shape path (radius theta, angle chi);
    (b) psi(t); (c) the inputs; (d) the costates. Returns the Figure; saves a PNG to
    ``path`` (dpi 120) if given.
    """
    from matplotlib.figure import Figure

    ts, qs, us = np.asarray(ts), np.asarray(qs), np.asarray(us)
    theta, chi, psi = qs[:, 0], qs[:, 1], qs[:, 2]
    fig = Figure(figsize=(10, 7.5), layout="constrained")
    ax = fig.add_subplot(2, 2, 1, projection="polar")
    ax.plot(chi, theta, color="tab:purple", lw=1.5)
    ax.plot(chi[0], theta[0], "o", color="k", label="start = end")
    ax.plot(0, 0, "+", color="0.4", ms=10, label="straight cat")
    ax.set_rmax(1.15 * theta.max())
    ax.legend(loc="lower left", bbox_to_anchor=(-0.2, -0.1), fontsize=8)
    ax.set_title("(a) shape path: radius $\\theta$, angle $\\chi$ [rad]", size=10)
    ax = fig.add_subplot(2, 2, 2)
    ax.plot(ts, psi, color="tab:green", label=r"$\psi$")
    if turn is not None:
        ax.axhline(psi[0] + turn, ls="--", color="0.3", label=f"target (mod $2\\pi$) {turn:+.4f}")
    ax.set(xlabel="t [s]", ylabel=r"$\psi$ [rad]", title=r"(b) overall rotation $\psi$ about $e_2$")
    ax.legend()
    ax = fig.add_subplot(2, 2, 3)
    for k, c in enumerate(("tab:blue", "tab:orange")):
        ax.plot(ts, us[:, k], color=c, label=rf"$\dot w_{k + 1}$ (Pontryagin)")
        if us_check is not None:
            ax.plot(ts, np.asarray(us_check)[:, k], "--", color="k", lw=0.8,
                    label="direct" if k == 0 else None)
    ax.set(xlabel="t [s]", ylabel="input [rad/s]", title="(c) optimal shape velocities")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 4)
    if ps is not None:
        for k, name in enumerate((r"$p_{w_1}$", r"$p_{w_2}$", r"$p_\phi$")):
            ax.plot(ts, np.asarray(ps)[:, k], label=name)
        ax.legend(fontsize=8)
    ax.set(xlabel="t [s]", ylabel="costate [J s/rad]", title="(d) costates of the extremal")
    for ax in fig.axes[1:]:
        ax.grid(alpha=0.3)
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def somersault_animation(cat, ts, qs, path, frames=36, fps=12, *, elev=_ELEV, azim=_AZIM):
    """GIF of the cat moving through configurations ``qs`` (N, 3) = (theta, chi, psi)
    [rad] at times ``ts`` [s] (interpolated linearly to ``frames`` frames); written with
    matplotlib's Pillow writer to ``path``."""
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.figure import Figure

    ts, qs = np.asarray(ts), np.asarray(qs)
    times = np.linspace(ts[0], ts[-1], frames)
    qf = np.stack([np.interp(times, ts, qs[:, k]) for k in range(3)], -1)
    fig = Figure(figsize=(4, 4))
    ax = fig.add_subplot(projection="3d")

    def draw(i):
        ax.clear()
        draw_cat(ax, cat, qf[i], elev=elev, azim=azim)
        ax.set_title(rf"$t$ = {times[i]:.2f} s, $\psi$ = {qf[i, 2]:+.2f} rad", fontsize=10)

    FuncAnimation(fig, draw, frames=frames).save(path, writer=PillowWriter(fps=fps), dpi=80)
