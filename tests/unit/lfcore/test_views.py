"""Perspective views and refocusing (lfcore.views) against point sources rendered at known depths."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.chief_ray import project
from lfcore.render import LightFieldRenderer
from lfcore.views import (
    Lattice,
    nominal_lattice,
    refocus,
    refocus_stack,
    sample_views,
    view_mosaic,
    view_offsets,
    view_pupil_mm,
    view_shifts_px,
)
from lfcore.volume import VolumeGrid
from lfcore.white import micro_image_centres


@pytest.fixture(scope="module")
def renderer(tiny_rig):
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 200_000})
    return LightFieldRenderer(tiny_rig.camera[0], cfg, wavelength_nm=532.0, device="cpu")


def _point(renderer, xyz, seed=2):
    return renderer.irradiance(np.array([xyz], dtype=np.float64), 50_000.0, seed=seed)


def test_nominal_lattice_is_the_white_images_micro_image_centres(tiny_rig) -> None:
    cam = tiny_rig.camera[0].model_copy(update={"mla_rotation_deg": 0.7, "mla_offset_um": (13.0, -6.0)})
    lat = nominal_lattice(cam)
    centres = micro_image_centres(cam)
    # every micro-image centre is a lattice node (whole indices)
    n = (centres - np.asarray(lat.origin_px)) @ np.linalg.inv(lat.basis_px)
    assert np.abs(n - np.rint(n)).max() < 1e-9
    assert lat.pitch_px == pytest.approx(cam.pixels_per_lenslet * (1 + cam.mla_focal_length_mm
                                                                    / cam.image_distance_mm), rel=1e-12)


def test_a_view_samples_every_micro_image_at_one_offset() -> None:
    # a synthetic image whose value is the column: view (du, dv) of node n reads column c_n + du
    lat = Lattice(origin_px=(50.3, 40.6), basis_px=np.array([[9.7, 0.0], [0.0, 9.7]]), grid="square")
    img = np.tile(np.arange(100, dtype=np.float32) + 0.5, (80, 1))
    v = sample_views(img, lat)
    c = lat.centres(v.n1, v.n2)
    for k, (du, _dv) in enumerate(v.offsets_px):
        assert np.allclose(v.images[k][v.inside], (c[..., 0] + du)[v.inside], atol=1e-4)
    assert (np.hypot(*v.offsets_px.T) <= 0.5 * 9.7 - 0.5 + 1e-9).all()
    assert len(view_offsets(lat, radius_px=2.0)) == 13


def test_views_of_a_point_shift_with_the_pupil_by_the_model_parallax(tiny_rig, renderer) -> None:
    cam = tiny_rig.camera[0]
    xyz = (0.013, -0.021, 0.45)
    v = sample_views(_point(renderer, xyz), nominal_lattice(cam))
    c = v.lattice.centres(v.n1, v.n2)
    total = v.images.sum(axis=(1, 2))
    lit = total > 0.2 * total.mean()
    seen = np.array([(img[..., None] * c).sum(axis=(0, 1)) / img.sum() for img in v.images[lit]])
    expected = np.array([project(cam, np.array(xyz), pupil_mm=tuple(a))
                         for a in view_pupil_mm(cam, v.offsets_px[lit])])
    # the parallax across the views: a straight line through the model's with slope 1 (each
    # view samples the point only at lenslet centres, so single views scatter by a few pixels)
    for axis in (0, 1):
        slope, _ = np.polyfit(expected[:, axis], seen[:, axis], 1)
        assert slope == pytest.approx(1.0, abs=0.15)
    spread = np.ptp(expected, axis=0)
    assert spread.max() > 1.2 * v.lattice.pitch_px  # the test point has parallax of more than a lenslet
    # the model's shift of a plane is the same for every point of it
    sh = view_shifts_px(cam, v.offsets_px[lit], xyz[2])
    assert np.allclose(sh, expected - project(cam, np.array(xyz)), atol=1e-6)


@pytest.mark.parametrize("z", [-0.6, -0.3, 0.45, 0.7])
@pytest.mark.parametrize("upsample", [1, 4])
def test_a_point_refocuses_sharpest_at_its_depth_within_one_voxel(tiny_rig, renderer, z, upsample) -> None:
    cam = tiny_rig.camera[0]
    dz = VolumeGrid.from_rig(tiny_rig).voxel_mm[2]
    v = sample_views(_point(renderer, (0.02, 0.01, z)), nominal_lattice(cam))
    depths = np.arange(-0.8, 0.8 + 1e-9, dz)
    stack = refocus_stack(v, cam, depths, upsample=upsample)
    sharpness = stack.reshape(len(depths), -1).var(axis=1)
    assert abs(depths[np.argmax(sharpness)] - z) <= dz + 1e-9


def test_refocusing_on_the_focal_plane_is_the_mean_of_the_views(tiny_rig, renderer) -> None:
    cam = tiny_rig.camera[0]
    v = sample_views(_point(renderer, (0.0, 0.0, 0.3)), nominal_lattice(cam))
    assert np.abs(view_shifts_px(cam, v.offsets_px, 0.0)).max() < 1e-9
    plane = refocus(v, cam, 0.0)
    assert np.allclose(plane[v.inside], v.images.mean(axis=0)[v.inside], rtol=1e-5, atol=1e-6)
    assert refocus(v, cam, 0.0, upsample=3).shape == (3 * v.inside.shape[0], 3 * v.inside.shape[1])


def test_white_normalised_views_are_flat(tiny_rig) -> None:
    from lfcore.white import WhiteImageConfig, white_irradiance

    cam = tiny_rig.camera[0]
    white = white_irradiance(cam, config=WhiteImageConfig(vignetting=0.4))
    v = sample_views(0.5 * white, nominal_lattice(cam), white=white)
    assert np.allclose(v.images[:, v.inside], 0.5, atol=1e-4)


def test_pictures_have_the_views_shapes(tiny_rig, renderer) -> None:
    cam = tiny_rig.camera[0]
    v = sample_views(_point(renderer, (0.0, 0.0, 0.3)), nominal_lattice(cam))
    pic = v.picture(v.centre)
    assert pic.shape[0] == v.inside.shape[0] and pic.shape[1] <= v.inside.shape[1]
    m = view_mosaic(v)
    m_tiles = 2 * int(np.abs(v.offsets_px).max()) + 1
    assert m.shape == (m_tiles * (pic.shape[0] + 1) - 1, m_tiles * (pic.shape[1] + 1) - 1)
    with pytest.raises(ValueError, match="upsample"):
        refocus(v, cam, 0.0, upsample=0)
    with pytest.raises(ValueError, match="no micro-image"):
        sample_views(np.zeros((4, 4)), v.lattice)
