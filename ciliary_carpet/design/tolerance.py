"""The fabrication tolerance of a design: how its residual spreads when the cilia come out with
curvature errors (:class:`ToleranceStudy`, :func:`tolerance_study`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.design.model import DesignModel, solver_threads
from ciliary_carpet.design.result import Design

__all__ = ["ToleranceStudy", "tolerance_study", "DEFAULT_SAMPLES"]

DEFAULT_SAMPLES = 64
"""How many samples a tolerance study draws unless told (``[target] samples``)."""


@dataclass(frozen=True)
class ToleranceStudy:
    """How a design's residual spreads when the cilia come out with curvature errors.

    Model: chi_j -> chi_j (1 + sigma eps_j), eps_j independent standard normal (a relative
    fabrication error; a perturbed |chi_N| beyond the flutter cutoff stands still). Each sample's
    flow is the design model plus the full model's defect at the design (:class:`~ciliary_carpet.design.model.DesignModel`),
    one Stokeslet sum per sample. sigma; samples; seed; nominal_rms: the design's residual;
    mean_rms, std_rms, p10_rms, p90_rms: over the samples; sampling_error: std_rms /
    sqrt(samples), the standard error of mean_rms; rms (samples,): every sample's residual.
    Method error: the defect is frozen at the nominal layout, so a sample's flow misses how the
    near field beyond the dipole changes with chi; measured against brute-force full-model
    samples in the tests (well below the sampling error for sigma <= 0.1)."""

    sigma: float
    samples: int
    seed: int
    nominal_rms: float
    mean_rms: float
    std_rms: float
    p10_rms: float
    p90_rms: float
    sampling_error: float
    rms: np.ndarray
    sigma_psi: float = 0.0

    def summary(self) -> dict:
        out = {"sigma": self.sigma, "samples": self.samples, "seed": self.seed, "nominal_rms": self.nominal_rms,
               "mean_rms": self.mean_rms, "std_rms": self.std_rms, "p10_rms": self.p10_rms,
               "p90_rms": self.p90_rms, "sampling_error": self.sampling_error,
               "method": "sampled; design model + the full model's defect at the design"}
        if self.sigma_psi:
            out["sigma_psi"] = self.sigma_psi
        return out


def tolerance_study(carpet: Carpet, d: Design, sigma: float, samples: int = DEFAULT_SAMPLES,
                    seed: int = 0, sigma_psi: float = 0.0) -> ToleranceStudy:
    """The expected residual of design ``d`` on ``carpet`` (its designed carpet) and its spread
    under a relative chi_N error ``sigma`` (see :class:`ToleranceStudy`) and, for a standing
    carpet's design (``d.azimuth``), an azimuth error ``sigma_psi`` [rad] (psi_j -> psi_j +
    sigma_psi eps'_j; its flow the surface design model, :class:`~ciliary_carpet.design.surface_model.SurfaceModel`,
    plus the full model's defect at the design)."""
    sg, sp = float(sigma), float(sigma_psi)
    if not (math.isfinite(sg) and sg >= 0):
        raise ValueError(f"sigma must be a finite number >= 0 (a relative chi_N error), got {sigma!r}")
    if not (math.isfinite(sp) and sp >= 0):
        raise ValueError(f"sigma_psi must be a finite number >= 0 (an azimuth error in rad), got {sigma_psi!r}")
    if sp > 0 and d.azimuth is None:
        raise ValueError("sigma_psi is the azimuth error of a standing carpet's design; this design is planar")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
    chi = np.asarray(d.chi_N, dtype=float)
    if d.azimuth is not None:
        from ciliary_carpet.design.surface_model import SurfaceModel

        psi = np.asarray(d.azimuth, dtype=float)
        sm = SurfaceModel(carpet, d.control, d.height)

        def velocity(c, p):
            return sm.flow(np.clip(c, 0.0, None), p)[0][:, :2]

        shift = d.achieved - velocity(chi, psi)
    else:
        dm = DesignModel(carpet, d.control, chi)

        def velocity(c, p):
            return dm.velocity(c)

        psi = None
        shift = d.achieved - velocity(chi, psi)
    P = d.control.shape[0]
    if d.kind == "velocity":
        scale = math.sqrt(float(np.sum(d.target ** 2)) / P)
    rng = np.random.default_rng(seed)
    rms = np.empty(int(samples))
    with solver_threads(3 * carpet.n * P):
        for k in range(int(samples)):
            c_k = chi * (1.0 + sg * rng.standard_normal(chi.size))
            p_k = None if psi is None else psi + sp * rng.standard_normal(psi.size)
            u = velocity(c_k, p_k) + shift
            if d.kind == "angle":
                r = np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(d.target[:, 0] + 1j * d.target[:, 1]))
            else:
                r = np.linalg.norm(u - d.target, axis=1) / scale
            rms[k] = math.sqrt(float(np.mean(r ** 2)))
    sd = float(rms.std(ddof=1)) if rms.size > 1 else 0.0
    return ToleranceStudy(sigma=sg, samples=int(samples), seed=int(seed), nominal_rms=d.residual_rms,
                          mean_rms=float(rms.mean()), std_rms=sd, p10_rms=float(np.percentile(rms, 10)),
                          p90_rms=float(np.percentile(rms, 90)), sampling_error=sd / math.sqrt(rms.size), rms=rms,
                          sigma_psi=sp)

