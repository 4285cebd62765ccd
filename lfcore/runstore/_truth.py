"""The ground truth of a synthetic run: ``truth/`` particles, brightness and pair times."""

from __future__ import annotations

from typing import Any

import numpy as np

from lfcore._deprecation import keyword_options
from lfcore.flows import Flow, flow_from_params
from lfcore.runstore._common import Part, RunStoreError, run_array
from lfcore.runstore._coords import pair_times_s
from lfcore.runstore._schema import validated

#: The arrays of ``truth/``, with their data types (``t0_s`` is missing from older stores).
TRUTH_ARRAYS = {"particles": np.float64, "brightness": np.float32, "t0_s": np.float64}


class Truth(Part):
    """What a synthetic run was rendered from, so that every error can be measured against it."""

    @keyword_options("t0_s", since="0.1.0")
    def write_truth(self, particles_mm: np.ndarray, brightness: np.ndarray, flow: dict[str, Any], *,
                    t0_s: np.ndarray | None = None, **attrs: Any) -> None:

        """Store the ground truth of a synthetic run.

        Parameters
        ----------
        particles_mm
            (pairs, 2, n, 3) float world positions (x, y, z) in mm of every particle in
            frames A and B of every pair.
        brightness
            (pairs, 2, n) signal of each particle in counts (laser sheet included).
        flow
            The flow's name and parameters (:meth:`lfcore.flows.Flow.params`).
        t0_s
            (pairs,) time of each pair's first pulse on the flow's clock, s, kept as
            ``truth/t0_s``; None: pair / ``timing.rate_hz`` (a simulated lab that shows a pool
            of pairs over and over passes the times of the pairs it showed).
        **attrs
            More JSON-compatible attributes (seeding density, seed, render settings).
        """
        if "truth" in self.group:
            del self.group["truth"]
        g = self.group.create_group("truth")
        g.attrs.update({"flow": flow, **attrs})
        p = np.asarray(particles_mm, dtype=np.float64)
        run_array(g, "particles", "mm", ["pair", "frame", "particle", "xyz"], "true particle positions",
                  shape=p.shape, chunks=(1, 2, *p.shape[2:]), dtype=np.float64)[...] = p
        b = np.asarray(brightness, dtype=np.float32)
        run_array(g, "brightness", "counts", ["pair", "frame", "particle"], "signal of each particle",
                  shape=b.shape, chunks=(1, 2, b.shape[2]), dtype=np.float32)[...] = b
        t0 = self._pair_times_s() if t0_s is None else np.asarray(t0_s, dtype=np.float64)
        if t0.shape != (p.shape[0],):
            raise ValueError(f"t0_s must hold one time per pair ({p.shape[0]}), got shape {t0.shape}")
        run_array(g, "t0_s", "s", ["pair"], "time of each pair's first pulse on the flow's clock",
                  shape=t0.shape, chunks=t0.shape, dtype=np.float64)[...] = t0

    def _pair_times_s(self) -> np.ndarray:
        t = pair_times_s(self.n_pairs, self.timing)
        return np.zeros(self.n_pairs) if t is None else t

    def truth_flow(self) -> Flow | None:
        """The flow the truth was rendered from (:func:`lfcore.flows.flow_from_params` of its
        ``flow`` attribute), or None for a recorded run or points given by the user.

        Raises
        ------
        RunStoreError
            If the attribute makes no flow lfpiv knows (an unknown name, parameters that do not
            fit it), one line.
        """
        if "truth" not in self.group:
            return None
        flow = validated(self.path, "truth", self.group["truth"].attrs)["flow"]  # the attributes alone, no arrays
        if flow.get("name") == "static-points":
            return None
        try:
            return flow_from_params(flow)
        except ValueError as exc:
            raise RunStoreError(f"{self.path}: truth/ attribute flow is {flow!r}, not a flow lfpiv knows ({exc}) "
                                "(truth/zarr.json was edited or damaged); restore it from a copy of the run") from None

    def truth(self) -> dict[str, Any] | None:
        """``{"particles", "brightness", "t0_s", "attrs"}`` of a synthetic run, or None if recorded.

        ``t0_s`` (pairs,): when each pair's first pulse fired on the flow's clock, s, the time
        to evaluate the truth flow at (pair / ``timing.rate_hz`` for stores written before it
        was kept).
        """
        if "truth" not in self.group:
            return None
        g = self.group["truth"]
        missing = [n for n in ("particles", "brightness") if n not in g]
        if missing:
            raise RunStoreError(f"{self.path}: truth/ has no {missing[0]} (the run was interrupted while its "
                                "truth was written); render it again with --overwrite")
        attrs = validated(self.path, "truth", g.attrs)
        t0 = g["t0_s"][...] if "t0_s" in g else self._pair_times_s()
        return {"particles": g["particles"][...], "brightness": g["brightness"][...], "t0_s": t0,
                "attrs": dict(attrs)}
