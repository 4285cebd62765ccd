"""Tracks through a time-resolved series (lfcore.track.link_series, fit_series, pair_tracks) from
known motions of known point sets."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcore.track import (
    SeriesSettings,
    SeriesTracks,
    TrackSettings,
    field_of_tracks,
    fit_series,
    link_series,
    pair_tracks,
    predict_series,
)
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(20, 64, 64), voxel_mm=(0.01, 0.01, 0.05), origin_mm=(-0.315, -0.315, -0.475))
VOXEL = np.asarray(GRID.voxel_mm)


def _points(n, seed):
    """n points away from the faces, none within a voxel of another (IPR merges such particles,
    and which of two is which is then anyone's guess)."""
    rng = np.random.default_rng(seed)
    lo = np.asarray(GRID.origin_mm) + 6 * VOXEL  # away from the faces
    size = VOXEL * (np.asarray(GRID.shape[::-1]) - 13)
    p = lo + rng.random((2 * n, 3)) * size
    d, _ = cKDTree(p / VOXEL).query(p / VOXEL, k=2)
    return p[d[:, 1] > 1.0][:n]


def _shuffled(frames, seed):
    """Each frame's particles in a random order, and where each true particle went."""
    rng = np.random.default_rng(seed)
    out, where = [], []
    for f in frames:
        perm = rng.permutation(len(f))
        out.append(f[perm])
        where.append(np.argsort(perm))  # true particle i is row where[i]
    return out, where


def _full_and_true(tracks, where, n, frames):
    """How many tracks run through every frame, and whether each of them follows one true particle."""
    full = np.nonzero(tracks.lengths() == frames)[0]
    right = 0
    for t in full:
        rows = tracks.row[tracks.track == t]
        truth = [np.nonzero(where[f] == r)[0][0] for f, r in enumerate(rows)]
        right += len(set(truth)) == 1
    return len(full), right


def test_a_uniform_displacement_through_six_frames_is_linked_into_full_tracks():
    a = _points(250, 0)
    step = np.array([1.7, -1.2, 0.6]) * VOXEL  # per frame
    frames = [a + k * step for k in range(6)]
    shuffled, where = _shuffled(frames, 1)
    tracks = link_series(shuffled, GRID, settings=TrackSettings(search_voxels=(3.0, 3.0, 1.5)))
    full, right = _full_and_true(tracks, where, len(a), 6)
    assert full == len(a) and right == len(a)  # every particle followed through all six frames
    assert tracks.n_tracks == len(a)


def test_a_rotation_through_six_frames_is_linked_into_full_tracks():
    a = _points(400, 2)
    omega = 0.01  # rad a frame about z: up to 4 voxels a frame at the corners
    frames = []
    for k in range(6):
        c, s = np.cos(k * omega), np.sin(k * omega)
        frames.append(np.column_stack([a[:, 0] * c - a[:, 1] * s, a[:, 0] * s + a[:, 1] * c, a[:, 2]]))
    rng = np.random.default_rng(3)
    noisy = [f + rng.normal(scale=0.05, size=f.shape) * VOXEL for f in frames]
    shuffled, where = _shuffled(noisy, 4)
    tracks = link_series(shuffled, GRID, settings=TrackSettings(search_voxels=(5.0, 5.0, 1.0), bin_voxels=(8, 8, 5)))
    full, right = _full_and_true(tracks, where, len(a), 6)
    assert full >= 0.97 * len(a)
    assert right == full  # no track jumps from one particle to another


def test_the_polynomial_fit_reduces_a_known_noise():
    # a curved path (constant acceleration) sampled with 0.1 voxel of noise through 10 frames
    rng = np.random.default_rng(5)
    a = _points(300, 6)
    vel = np.array([1.0, 0.5, 0.2]) * VOXEL
    acc = np.array([0.1, -0.05, 0.0]) * VOXEL
    true = [a + k * vel + 0.5 * k * k * acc for k in range(10)]
    noise = 0.1 * VOXEL
    frames = [t + rng.normal(size=t.shape) * noise for t in true]
    ser = SeriesSettings(fit_frames=6)
    tracks = fit_series(link_series(frames, GRID, settings=TrackSettings(search_voxels=(3.0, 3.0, 1.0))), series=ser)
    assert np.all(tracks.lengths() == 10)
    truth = np.array([true[f][r] for f, r in zip(tracks.frame, tracks.row, strict=True)])
    before = np.sqrt(np.mean(((tracks.position_mm - truth) / VOXEL) ** 2, axis=0))
    after = np.sqrt(np.mean(((tracks.fitted_mm - truth) / VOXEL) ** 2, axis=0))
    assert np.allclose(before, 0.1, rtol=0.1)
    assert np.all(after < 0.75 * before)  # a 2nd-order fit through 6 frames: about 0.6 of the noise
    # the displacement over a pair at its mid-time: a pair alone has sqrt(2) x 0.1 voxel of noise
    # the displacement over a pair at its mid-time: one pair's tracks alone have sqrt(2) x 0.1 = 0.14
    # voxel of noise; a fit centred on the pair (2 of 6 frames either side) about 0.024, one at the
    # series' ends (its window all on one side) about 0.07
    for pair, most in ((0, 0.09), (2, 0.035), (4, 0.09)):
        pa, pb, ids = pair_tracks(tracks, pair, series=ser)
        assert len(ids) == len(a)
        rows = [tracks.row[(tracks.track == t) & (tracks.frame == 2 * pair)][0] for t in ids]
        exact = vel + (2 * pair + 0.5) * acc  # the velocity at the mid-time, times one frame
        err = ((pb - pa) - exact) / VOXEL
        assert np.all(np.sqrt(np.mean(err ** 2, axis=0)) < most)
        assert np.sqrt(np.mean(((pa - np.array(true[2 * pair])[rows]) / VOXEL) ** 2)) < 0.095  # the noise: 0.1


def test_short_tracks_are_not_fitted_and_settings_are_checked():
    a = _points(50, 7)
    frames = [a, a + VOXEL, a + 2 * VOXEL]  # three frames: too short for min_frames 4
    tracks = fit_series(link_series(frames, GRID))
    assert np.all(np.isnan(tracks.fitted_mm))
    assert len(pair_tracks(tracks, 0)[2]) == 0
    with pytest.raises(ValueError, match="at least 3 frames"):
        SeriesSettings(fit_frames=2)
    with pytest.raises(ValueError, match="link_voxels"):
        SeriesSettings(link_voxels=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="bridge_frames"):
        SeriesSettings(bridge_frames=-1)
    assert "bridge_frames" not in SeriesSettings().as_dict()  # vectors tracked before it read the same
    assert SeriesSettings(bridge_frames=2).as_dict()["bridge_frames"] == 2


def _missing(n_frames, n, share, seed):
    """Which particles each frame misses: ``share`` of them at random, as reconstruction does."""
    rng = np.random.default_rng(seed)
    return [rng.random(n) < share for _ in range(n_frames)]


def test_bridged_gaps_keep_the_tracks_of_particles_missed_in_a_frame_or_two():
    # a curved path through 10 frames (0.05 voxel of noise), each frame missing 12% of its particles:
    # without bridging, a track breaks at every miss and a pair loses each particle missed in A or B
    n, nf = 250, 10
    a = _points(n, 11)
    vel = np.array([1.5, -1.0, 0.4]) * VOXEL
    acc = np.array([0.08, 0.04, 0.0]) * VOXEL
    rng = np.random.default_rng(12)
    true = [a + k * vel + 0.5 * k * k * acc for k in range(nf)]
    gone = _missing(nf, n, 0.12, 13)
    frames = [(t + rng.normal(size=t.shape) * 0.05 * VOXEL)[~g] for t, g in zip(true, gone, strict=True)]
    ids = [np.nonzero(~g)[0] for g in gone]  # each row's true particle
    settings = TrackSettings(search_voxels=(3.0, 3.0, 1.0))
    out = {}
    for bridge in (0, 2):
        ser = SeriesSettings(bridge_frames=bridge)
        tracks = fit_series(link_series(frames, GRID, settings=settings, series=ser), series=ser)
        owner = np.array([ids[f][r] for f, r in zip(tracks.frame, tracks.row, strict=True)])
        one = [len(set(owner[tracks.track == t])) == 1 for t in range(tracks.n_tracks)]
        long = tracks.lengths() >= 7
        out[bridge] = (int(long.sum()), bool(np.all(np.asarray(one)[long])))
        pa, pb, _ = pair_tracks(tracks, 2, series=ser)
        exact = vel + 4.5 * acc  # the velocity at pair 2's mid-time, times one frame
        err = np.sqrt(np.mean((((pb - pa) - exact) / VOXEL) ** 2, axis=0))
        out[bridge] += (len(pa), err)
    # bridged: nearly every particle on one track of 7 frames or more, no track jumping particles
    assert out[2][0] >= 0.9 * n and out[2][1]
    assert out[0][0] < 0.6 * n  # unbridged: a track breaks at each miss
    # pair 2's tracks: nearly every particle (those missed in frame A or B too), at the known velocity
    assert out[2][2] >= 0.95 * n > 0.85 * n >= out[0][2]
    assert np.all(out[2][3] < 0.05), out[2][3]  # one pair's own two frames: 0.07 voxel of noise


def test_the_field_of_fitted_tracks_is_the_known_displacement():
    a = _points(300, 8)
    shift = np.array([1.5, 0.5, 0.3]) * VOXEL
    res = field_of_tracks(a, a + shift, GRID, settings=TrackSettings(bin_voxels=(16, 16, 5)))
    good = np.isfinite(res.field_mm[..., 0])
    assert good.mean() > 0.5 and not res.outlier.any()
    assert np.allclose(res.field_mm[good], shift, atol=1e-6)


def _known(paths):
    """SeriesTracks of known tracks: ``paths`` a list of (frames, (n, 3) positions mm)."""
    track = np.concatenate([np.full(len(f), t) for t, (f, _) in enumerate(paths)]).astype(np.int64)
    frame = np.concatenate([np.asarray(f) for f, _ in paths]).astype(np.int64)
    pos = np.vstack([p for _, p in paths])
    return SeriesTracks(track=track, frame=frame, row=np.zeros(len(track), np.int64), position_mm=pos,
                        fitted_mm=np.full_like(pos, np.nan))


def _nearest(pred, at):
    """Each point of ``at``'s distance to the nearest prediction, voxels (largest axis)."""
    return np.array([np.min(np.max(np.abs(pred - p) / VOXEL, axis=1)) for p in at])


def test_the_prediction_carries_known_tracks_on_by_their_own_paths():
    """Shake-the-Box's prediction of the next frame from known tracks: a straight path and a curved
    (second-order) one exactly, a track of two frames by its last step, a track whose particle was
    missed in the last frame still predicted, one missed longer not; a particle on no track near its
    neighbours' steps (exactly where they are one step: the next test)."""
    x0 = np.array([0.0, 0.0, 0.0])
    line = lambda t: x0 + np.array([1.3, -0.7, 0.4]) * VOXEL * t  # noqa: E731
    curve = lambda t: x0 + 0.05 + np.array([0.9 * t, 0.25 * t * t, -0.1 * t * t]) * VOXEL  # noqa: E731
    step = np.array([0.8, 0.5, -0.3]) * VOXEL
    two = np.array([[-0.1, 0.1, 0.0], [-0.1, 0.1, 0.0] + step])
    paths = [(range(6), np.array([line(t) for t in range(6)])),
             (range(2, 6), np.array([curve(t) for t in range(2, 6)])),
             ([4, 5], two),
             ([1, 2, 3, 4], np.array([line(t) + 0.1 for t in range(1, 5)])),  # missed in frame 5
             ([0, 1, 2], np.array([line(t) - 0.1 for t in range(3)])),  # ended long ago
             ([5], np.array([[0.1, -0.1, 0.0]]))]  # on no track: the others' steps predict it
    tracks = _known(paths)
    expect = np.array([line(6), curve(6), two[1] + step, line(6) + 0.1])
    pred = predict_series(tracks, 5)
    assert len(pred) == 5  # four tracks, one lone particle; the track that ended in frame 2 is not carried on
    assert np.all(_nearest(pred, expect) < 1e-9)
    # the lone particle by its neighbours' last steps (a straight line's, a curve's, a pair's: near step)
    lone = _nearest(pred, [paths[-1][1][0] + step])[0]
    assert lone < 1.0, lone
    # without the missed frame's leeway the track missed in frame 5 is not predicted
    assert len(predict_series(tracks, 5, missed=0)) == 4
    assert len(predict_series(_known([([0], np.zeros((1, 3)))]), 0)) == 0  # a lone particle, no tracks


def test_the_prediction_of_a_uniform_flow_from_linked_noisy_frames_is_within_the_noise():
    """link_series then predict_series (what ``lfpiv particles --along-pairs`` does between frames):
    a known uniform step with 0.05 voxel of noise, the prediction of frame 6 (a second-order
    polynomial through six positions: 1.8 times their noise per axis) within about that."""
    a = _points(200, 3)
    step = np.array([1.5, -0.8, 0.4]) * VOXEL
    rng = np.random.default_rng(4)
    frames = [a + k * step + rng.normal(size=a.shape) * 0.05 * VOXEL for k in range(6)]
    pred = predict_series(link_series(frames, GRID), 5)
    err = _nearest(pred, a + 6 * step)
    assert len(pred) >= 195
    assert np.median(err) < 0.15 and np.mean(err < 0.3) > 0.95, (np.median(err), np.mean(err < 0.3))


def test_a_lone_particle_is_carried_on_by_its_neighbours_known_step():
    """A particle found in the last frame only, among tracks of one known step (a uniform flow): few
    tracks (their median) or many (the local linear fit), it is predicted one step on, exactly; the
    tracks' own predictions too, and nothing else is predicted."""
    step = np.array([1.2, -0.6, 0.35]) * VOXEL
    lone = np.array([0.02, -0.03, 0.1])
    for n in (3, 12):
        starts = _points(n, 7)
        paths = [(range(4), np.array([a + t * step for t in range(4)])) for a in starts]
        paths.append(([3], lone[None, :]))
        pred = predict_series(_known(paths), 3)
        expect = np.vstack([starts + 4 * step, lone + step])
        assert len(pred) == n + 1
        assert np.all(_nearest(pred, expect) < 1e-9), (n, _nearest(pred, expect))


@pytest.mark.parametrize("bad", [(float("nan"), 1.0, 1.0), (1.0, float("inf"), 1.0), (1.0, 1.0, 0.0)])
def test_search_radii_must_be_positive_and_finite(bad):
    """A NaN radius passed ``min(v) <= 0`` and crashed the k-d tree far from the option; refused at once."""
    for make in (lambda: TrackSettings(search_voxels=bad), lambda: TrackSettings(refine_voxels=bad),
                 lambda: SeriesSettings(link_voxels=bad)):
        with pytest.raises(ValueError, match="three positive"):
            make()


def _vortex(n_bg, n_core, n_frames, seed, *, peak, core):
    """Points on the exact circular paths of a Lamb-Oseen vortex about the z axis (its peak speed
    ``peak`` voxel a frame at 1.12 ``core`` voxels from the axis), carried by a slow uniform drift,
    with 0.05 voxel of noise; ``n_core`` of them within 2 ``core`` of the axis. Returns the noisy
    frames and each point's speed about the axis (voxel a frame)."""
    rng = np.random.default_rng(seed)
    a = _points(n_bg + 400, seed)
    r = np.hypot(a[:, 0] / VOXEL[0], a[:, 1] / VOXEL[1])  # voxels (x and y voxels are the same)
    a = np.vstack([a[r < 2 * core][:n_core], a[r >= 2 * core][:n_bg]])
    r = np.hypot(a[:, 0], a[:, 1]) / VOXEL[0]
    theta = np.arctan2(a[:, 1], a[:, 0])
    circulation = peak * 1.12 * core / 0.638  # v(r) = circulation / r (1 - exp(-(r / core)^2))
    speed = circulation / r * (1.0 - np.exp(-((r / core) ** 2)))
    drift = np.array([0.4, 0.2, 0.1]) * VOXEL
    frames = [np.column_stack([r * np.cos(theta + k * speed / r) * VOXEL[0], r * np.sin(theta + k * speed / r)
                               * VOXEL[1], a[:, 2]]) + k * drift + rng.normal(scale=0.05, size=a.shape) * VOXEL
              for k in range(n_frames)]
    return frames, speed


def test_relinking_keeps_the_tracks_of_a_vortex_cores_fast_curved_paths():
    # a vortex core 6 voxels across, its particles up to 2.5 voxel a frame on circles turned by up to
    # 0.4 rad a frame: a straight line through a track's last positions misses the next by more than
    # --link-voxels, and the pair tracking's later passes, predicted by neighbours across the core,
    # miss them too; relinked, the pair tracking carries such tracks on
    n_core, n_bg, nf = 30, 300, 8
    frames, speed = _vortex(n_bg, n_core, nf, 21, peak=2.5, core=6.0)
    shuffled, where = _shuffled(frames, 22)
    out = {}
    for relink in (False, True):
        ser = SeriesSettings(relink=relink)
        tracks = link_series(shuffled, GRID, settings=TrackSettings(search_voxels=(4.0, 4.0, 1.0)), series=ser)
        lengths = tracks.lengths()
        full, wrong = np.zeros(len(speed), bool), 0
        for t in range(tracks.n_tracks):
            m = tracks.track == t
            owners = {int(np.nonzero(where[f] == r)[0][0]) for f, r in zip(tracks.frame[m], tracks.row[m], strict=True)}
            wrong += lengths[t] >= 4 and len(owners) > 1
            if lengths[t] == nf and len(owners) == 1:
                full[owners.pop()] = True
        out[relink] = (int(full[:n_core].sum()), int(full[n_core:].sum()), wrong)
    assert out[False][0] <= 0.5 * n_core and out[True][0] >= 0.8 * n_core  # the core's particles kept on their tracks
    assert out[True][1] >= out[False][1] >= 0.97 * n_bg  # the slow particles around it as before
    assert out[True][2] <= 2  # no more than a track or two jumping particles (without relinking: 0)
    assert SeriesSettings(relink=True).as_dict()["relink"] is True
    assert "relink" not in SeriesSettings().as_dict()  # vectors tracked before it read the same
