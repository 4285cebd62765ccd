"""Pictures a person would rather look at than numbers."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from calibration.store import CalibrationStore  # noqa: E402
from lfcore.files import replacing  # noqa: E402
from lfcore.rig import is_pinhole  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.errors import UsageError  # noqa: E402

__all__ = ["plot_camera_checks", "plot_grids", "plot_raw_images", "plot_reconstruction", "plot_rms", "plot_routes",
           "plot_vectors", "plot_views", "save_figure"]


def save_figure(fig, out: str | Path, *, dpi: float = 100) -> Path:
    """Write ``fig`` to ``out`` (its format from ``out``'s suffix, PNG without one) whole or not at
    all (:func:`lfcore.files.replacing`: an interrupt or a full disk leaves the earlier file), and
    free the figure.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    out = Path(out)
    try:
        with replacing(out) as tmp:
            fig.savefig(tmp, dpi=dpi, format=out.suffix.lstrip(".").lower() or "png")
    finally:
        plt.close(fig)
    return out


def _stretch(img: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(img, [1.0, 99.9])
    return float(lo), float(max(hi, lo + 1.0))


def plot_raw_images(store: RunStore, out: str | Path, pair: int = 0, zoom_lenslets: int = 12) -> Path:
    """Save a PNG of one pair's raw light-field images, one row per camera.

    Each row shows the whole frame A, then frames A and B enlarged around the sensor centre,
    where the lenslet images (discs under focused particles, single sub-aperture spots under
    defocused ones) and the particles' motion between A and B can be seen.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    out = Path(out)
    rig = store.rig
    truth = store.truth()
    flow = truth["attrs"]["flow"]["name"] if truth else "recorded"
    cams = rig.camera
    fig, axes = plt.subplots(len(cams), 3, figsize=(15, 5.2 * len(cams)), squeeze=False)
    for row, cam in zip(axes, cams, strict=True):
        a, b = store.frames(cam.name)[pair]
        lo, hi = _stretch(a)
        rows, cols = a.shape
        # a pinhole camera's particle images are a few pixels across: zoom on as many pixels as
        # the light-field camera's lenslets
        half = int(round(0.5 * zoom_lenslets * (4.0 if is_pinhole(cam) else cam.pixels_per_lenslet)))
        r0, c0 = max(0, rows // 2 - half), max(0, cols // 2 - half)
        r1, c1 = min(rows, rows // 2 + half), min(cols, cols // 2 + half)
        row[0].imshow(a, cmap="gray", vmin=lo, vmax=hi, interpolation="antialiased")
        row[0].add_patch(Rectangle((c0, r0), c1 - c0, r1 - r0, fill=False, edgecolor="tab:orange", lw=1.5))
        row[0].set_title(f"{cam.name}: frame A, {cols} x {rows} px")
        for ax, img, name in ((row[1], a, "A"), (row[2], b, "B")):
            ax.imshow(img[r0:r1, c0:c1], cmap="gray", vmin=lo, vmax=hi, interpolation="nearest",
                      extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
            across = f"{c1 - c0} px" if is_pinhole(cam) else f"{zoom_lenslets} lenslets"
            ax.set_title(f"frame {name}, centre ({across} across)")
        for ax in row:
            ax.set_xlabel("column (px)")
            ax.set_ylabel("row (px)")
    n_part = truth["particles"].shape[2] if truth else None
    extra = f", {n_part} particles per frame" if n_part else ""
    fig.suptitle(f"{store.path.name}: raw images of pair {pair} ({flow}{extra}, "
                 f"dt = {store.dt_s * 1e3:g} ms)")
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
    return out


def plot_reconstruction(store: RunStore, evals, out: str | Path) -> Path:
    """Save a PNG of the first evaluated volume: intensity against depth (the chapter's Fig. 4.9b)
    and maximum-intensity projections of the reconstruction and of the truth on the x-z plane.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from lfcore import metrics

    out = Path(out)
    e = evals[0]
    grid = store.volume_grid()
    vol = store.read_volume(e.pair, e.frame)
    truth = store.truth()
    e0 = metrics.truth_volume(grid, truth["particles"][e.pair, e.frame],
                              brightness=truth["brightness"][e.pair, e.frame])
    z = grid.axis_mm("z")
    x = grid.axis_mm("x")
    rig = store.rig
    lo = rig.volume.centre_mm[2] - 0.5 * rig.volume.size_mm[2]
    hi = rig.volume.centre_mm[2] + 0.5 * rig.volume.size_mm[2]
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.8))
    ax[0].plot(z, e.depth_profile / max(e.depth_profile.max(), 1e-30), label="reconstructed")
    ax[0].plot(z, e.truth_profile / max(e.truth_profile.max(), 1e-30), "--", label="truth (3-voxel blobs)")
    ax[0].axvspan(lo, hi, color="0.9", zorder=0, label="seeded region")
    ax[0].set_xlabel("z (mm)")
    ax[0].set_ylabel("mean intensity (normalised)")
    ax[0].legend()
    ax[0].set_title(f"pair {e.pair} frame {'AB'[e.frame]}: Q = {e.q:.3f}, recall {e.match.recall:.2f}")
    ext = (x[0], x[-1], z[0], z[-1])
    for a, v, name in ((ax[1], vol, "reconstruction"), (ax[2], e0, "truth")):
        a.imshow(v.max(axis=1), origin="lower", extent=ext, aspect="auto", cmap="magma")
        a.set_title(f"{name}: maximum over y")
        a.set_xlabel("x (mm)")
        a.set_ylabel("z (mm)")
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


def plot_vectors(store: RunStore, out: str | Path, pair: int = 0) -> Path:
    """Save a PNG of the in-plane vectors (u, v) on the middle z slice of a pair, over the
    out-of-plane vorticity w_z; beside it the truth flow on the same grid when the run has one.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from lfcore.metrics import grid_velocity
    from lfcore.vectors import vorticity

    out = Path(out)
    vec = store.vectors()
    x, y, z = vec["x_mm"], vec["y_mm"], vec["z_mm"]
    fields = [("measured", np.stack([vec[c][pair] for c in "uvw"], axis=-1))]
    truth = store.truth()
    if truth is not None and truth["attrs"].get("flow", {}).get("name") not in (None, "static-points"):
        t_mid = float(truth["t0_s"][pair]) + 0.5 * store.dt_s
        fields.append(("truth", grid_velocity(store.truth_flow(), x, y, z, t_mid)))
    k = len(z) // 2
    fig, axes = plt.subplots(1, len(fields), figsize=(6.2 * len(fields), 5.4), squeeze=False)
    wz_max = max(float(np.abs(vorticity(f, x, y, z)[k, ..., 2]).max()) for _, f in fields) or 1.0
    for ax, (name, f) in zip(axes[0], fields, strict=True):
        wz = vorticity(f, x, y, z)[k, ..., 2]
        im = ax.imshow(wz, origin="lower", extent=(x[0], x[-1], y[0], y[-1]), cmap="RdBu_r", vmin=-wz_max,
                       vmax=wz_max, aspect="equal", interpolation="bilinear")
        ax.quiver(x, y, f[k, ..., 0], f[k, ..., 1], color="k", angles="xy")
        ax.set_title(f"{name}: (u, v) at z = {z[k]:.3g} mm over vorticity w_z")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(im, ax=ax, label="w_z (1/s)", shrink=0.85)
    fig.suptitle(f"{store.path.name}: pair {pair}, {len(x)} x {len(y)} x {len(z)} vectors")
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


def plot_routes(routes: list[tuple[str, RunStore]], out: str | Path, pair: int = 0) -> Path:
    """Save a PNG of several runs' vectors of one pair, one row per run: the truth flow on the
    run's own grid (when the run has one) beside what the run measured, each the in-plane vectors
    (u, v) of the z plane nearest the volume's centre over the in-plane speed (blank where it
    measured none), on one colour scale and the volume's extent. The demo's two routes (volumes
    and correlation, particles and tracking) on one recording.

    Parameters
    ----------
    routes
        (label, run store) per row, each with ``vectors/`` holding ``pair``.
    out
        The PNG.
    pair
        The pair shown.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from lfcore.metrics import grid_velocity

    out = Path(out)
    rows = []
    for label, store in routes:
        vec = store.vectors()
        x, y, z = vec["x_mm"], vec["y_mm"], vec["z_mm"]
        k = int(np.argmin(np.abs(np.asarray(z) - float(store.rig.volume.centre_mm[2]))))
        panels = [(label, np.stack([vec[c][pair] for c in "uvw"], axis=-1).astype(np.float64)[k])]
        truth = store.truth()
        if truth is not None and truth["attrs"].get("flow", {}).get("name") not in (None, "static-points"):
            t_mid = float(truth["t0_s"][pair]) + 0.5 * store.dt_s
            panels.insert(0, ("truth on its grid", grid_velocity(store.truth_flow(), x, y, z[k:k + 1], t_mid)[0]))
        rows.append((x, y, z[k], panels))
    top = max(float(np.nanmax(np.hypot(p[..., 0], p[..., 1]), initial=0.0))
              for *_, panels in rows for _, p in panels) or 1.0
    cols = max(len(r[3]) for r in rows)
    vol = routes[0][1].rig.volume
    lo = np.asarray(vol.centre_mm) - 0.5 * np.asarray(vol.size_mm)
    hi = lo + np.asarray(vol.size_mm)
    fig, axes = plt.subplots(len(rows), cols, figsize=(4.6 * cols, 4.2 * len(rows)), squeeze=False,
                             constrained_layout=True)
    im = None
    for r, (x, y, zk, panels) in enumerate(rows):
        dx, dy = (x[1] - x[0] if len(x) > 1 else 1.0), (y[1] - y[0] if len(y) > 1 else 1.0)
        for c in range(cols):
            ax = axes[r][c]
            if c >= len(panels):
                ax.axis("off")
                continue
            label, p = panels[c]
            im = ax.imshow(np.hypot(p[..., 0], p[..., 1]), origin="lower", cmap="viridis", vmin=0.0, vmax=top,
                           extent=(x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2), aspect="equal")
            # arrows in mm: the peak speed a grid step long
            ax.quiver(x, y, p[..., 0], p[..., 1], color="w", angles="xy", scale_units="xy", scale=top / min(dx, dy))
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_title(f"{routes[r][0] if c == len(panels) - 1 else label}\n(u, v) at z = {zk:.3g} mm",
                         fontsize=10)
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
    if im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), label="in-plane speed (m/s)", shrink=0.8)
    fig.suptitle(f"pair {pair}: the same recording by each route, beside the truth on its grid")
    save_figure(fig, out, dpi=100)
    return out


def plot_grids(store: CalibrationStore, out: str | Path, lenslets: int = 8) -> Path:
    """Save a PNG: per camera, the white image around the sensor centre with the detected
    centres (inliers +, outliers x) and fitted nodes (o), and the residuals over the sensor.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    UsageError
        The store holds no microlens grid.
    """
    out = Path(out)
    names = [n for n in store.cameras if store.grid(n) is not None]
    if not names:
        raise UsageError(f"{store.path} holds no microlens grid; run 'lfpiv calibrate mla' first")
    fig, axes = plt.subplots(len(names), 2, figsize=(11, 5 * len(names)), squeeze=False)
    for row, name in zip(axes, names, strict=True):
        grid, white = store.grid(name), store.white(name)
        rows, cols = white.shape
        half = 0.5 * lenslets * grid.pitch_px
        cx, cy = cols / 2, rows / 2
        c0, c1 = int(max(0, cx - half)), int(min(cols, cx + half))
        r0, r1 = int(max(0, cy - half)), int(min(rows, cy + half))
        ax = row[0]
        ax.imshow(white[r0:r1, c0:c1], cmap="gray", extent=(c0, c1, r1, r0), interpolation="nearest")
        cen, fit, inl = grid.centres_px, grid.lattice_px(), grid.inliers
        box = (cen[:, 0] > c0) & (cen[:, 0] < c1) & (cen[:, 1] > r0) & (cen[:, 1] < r1)
        ax.plot(fit[box, 0], fit[box, 1], "o", mfc="none", mec="tab:cyan", ms=8, label="fitted lattice")
        ax.plot(cen[box & inl, 0], cen[box & inl, 1], "+", color="tab:green", ms=8, label="detected")
        ax.plot(cen[box & ~inl, 0], cen[box & ~inl, 1], "x", color="tab:red", ms=8, label="outlier")
        ax.set_title(f"{name}: white image at the sensor centre")
        ax.legend(loc="upper right", fontsize=8)
        ax = row[1]
        res = grid.residuals_px
        scale = max(float(np.percentile(np.hypot(*res[inl].T), 95)), 1e-3)
        ax.quiver(cen[inl, 0], cen[inl, 1], res[inl, 0], -res[inl, 1], np.hypot(*res[inl].T), angles="xy",
                  scale_units="xy", scale=scale / grid.pitch_px, cmap="viridis")
        ax.plot(cen[~inl, 0], cen[~inl, 1], "x", color="tab:red", ms=5)
        ax.set_xlim(0, cols)
        ax.set_ylim(rows, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: residuals (arrow of one pitch = {scale:.3f} px), RMS {grid.rms_px:.4f} px")
    fig.tight_layout()
    save_figure(fig, out, dpi=90)
    return out


def plot_rms(store: CalibrationStore, out: str | Path) -> Path:
    """Save a PNG of each fitted camera's reprojection RMS per plane against the stage position.

    Raises
    ------
    UsageError
        No camera has a fitted model.
    """
    names = [n for n in store.cameras if store.model(n) is not None]
    if not names:
        raise UsageError(f"{store.path} holds no fitted camera model; run 'lfpiv calibrate fit' first")
    fig, ax = plt.subplots(figsize=(7, 4))
    for name in names:
        m = store.model(name)
        rms = np.array([np.nan if v is None else v for v in m["plane_rms_px"]], dtype=float)
        line, = ax.plot(store.stage_mm(name), rms, "o-", label=f"{name} (all planes {m['rms_px']:.3f} px)")
        if m.get("soloff_plane_rms_px"):  # a pinhole camera's Soloff polynomial, beside its pinhole model
            soloff = np.array([np.nan if v is None else v for v in m["soloff_plane_rms_px"]], dtype=float)
            ax.plot(store.stage_mm(name), soloff, "s--", color=line.get_color(), mfc="none",
                    label=f"{name}, Soloff ({m['soloff_rms_px']:.3f} px)")
    ax.set_xlabel("stage position, mm")
    ax.set_ylabel("RMS reprojection error, px")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title("dot reprojection error per plane")
    fig.tight_layout()
    out = Path(out)
    save_figure(fig, out, dpi=90)
    return out


def plot_views(result, out: str | Path) -> Path:
    """Save a PNG of a frame's perspective views (:class:`lfpiv.jobs.views.ViewsResult`): the mosaic
    of every view (tiled as the micro-image holds them), the central view and each refocused plane.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    out = Path(out)
    planes = result.plane_images()
    n = 2 + len(planes)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.2 * rows), squeeze=False)
    pics = [(result.mosaic, f"{len(result.views.offsets_px)} perspective views (by offset u, v)"),
            (result.centre_view, "central view (u, v = 0, 0)")]
    pics += [(img, f"refocused at z = {z:+.3f} mm") for z, img in zip(result.depths_mm, planes, strict=True)]
    for ax, (img, title) in zip(axes.flat, pics, strict=False):
        # views divided by a white image have a few bright samples where the white is dim
        lo, hi = (float(np.percentile(img, 1.0)), float(np.percentile(img, 99.5))) if img.size else (0.0, 1.0)
        hi = max(hi, lo + 1e-6)
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.suptitle(f"camera {result.camera}: lattice from {result.lattice_source}", fontsize=9)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


def plot_camera_checks(checks, out: str | Path) -> Path:
    """Save a PNG of the checks before recording (:class:`lfcore.camera_checks.CameraCheck`, one
    row per camera): the histogram with full scale marked, the seeding against the chapter's
    range, and the refocused plane (or raw image) the camera shows.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from lfcore.camera_checks import MAX_PPM, MIN_PPM, PPP_RANGE, RECOMMENDED_PPM

    out = Path(out)
    fig, axes = plt.subplots(len(checks), 3, figsize=(14, 4.0 * len(checks)), squeeze=False)
    for row, c in zip(axes, checks, strict=True):
        centres = 0.5 * (c.bin_edges[:-1] + c.bin_edges[1:])
        row[0].bar(centres, np.maximum(c.histogram, 1), width=np.diff(c.bin_edges), color="tab:blue", log=True)
        row[0].axvline(c.full_scale, color="tab:red", ls="--", label="full scale (recommended: nothing here)")
        row[0].set_title(f"{c.camera}: histogram, {100 * c.saturated_fraction:.3f}% saturated", fontsize=9)
        row[0].set_xlabel("counts")
        row[0].legend(fontsize=8)
        if c.ppm is not None:
            value, lo, hi, best, unit = c.ppm, MIN_PPM, MAX_PPM, RECOMMENDED_PPM, "PPM"
        else:
            value, lo, hi, best, unit = c.ppp, PPP_RANGE[0], PPP_RANGE[1], None, "PPP"
        top = max(2.0 * hi, 1.2 * min(value, 10 * hi))
        row[1].axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"fine ({lo}-{hi} {unit})")
        if best is not None:
            row[1].axhline(best, color="tab:green", label=f"recommended {best} {unit}")
        row[1].bar([0], [min(value, top)], color="tab:blue", width=0.5)
        row[1].set_xlim(-1, 1)
        row[1].set_ylim(0, top)
        row[1].set_xticks([])
        row[1].set_ylabel(unit)
        fill = f", fill {c.fill:.2f}" if c.fill is not None else ""
        row[1].set_title(f"seeding {value:.3g} {unit}{fill}", fontsize=9)
        row[1].legend(fontsize=8)
        lo_, hi_ = _stretch(c.preview)
        row[2].imshow(c.preview, cmap="gray", vmin=lo_, vmax=hi_, interpolation="nearest")
        row[2].set_title(c.preview_label, fontsize=9)
        row[2].set_xticks([])
        row[2].set_yticks([])
    fig.tight_layout()
    save_figure(fig, out, dpi=90)
    return out
