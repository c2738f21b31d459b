"""Stokes flow of point forces: Green's functions and the backends that sum them.

``u(x_i) = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j``, the one sum every flow of the package is made of.
This package is the layer's front door: the names below are all a user or another layer needs.
Its modules, each one noun, from the bottom up:

:mod:`~ciliary_carpet.stokes.kernel`
    The Green's functions ``G`` (:class:`Kernel` and its registry :data:`KERNELS`): each one's pair
    formula, numpy reference, level-of-detail constants and symmetry.
:mod:`~ciliary_carpet.stokes.backend`
    :class:`Backend`, the contract of a backend, and the inputs it may assume.
:mod:`~ciliary_carpet.stokes.direct`, :mod:`~ciliary_carpet.stokes.fmm`, :mod:`~ciliary_carpet.stokes.cuda`
    The backends: :class:`Direct` (numba, CPU), :class:`FMM` (fmm3dpy), :class:`Cuda` (NVIDIA GPU).
:mod:`~ciliary_carpet.stokes.precision`
    Single precision: the shift and rounding of the inputs and the error bound that the fp32
    sums of :class:`Direct` and :class:`Cuda` share.
:mod:`~ciliary_carpet.stokes.dispatch`
    The front doors :func:`stokeslet_velocity` and :func:`stokeslet_velocity_ranges`, the choice
    :class:`Auto`, and the backends by name (:data:`BACKENDS`, :func:`backend_named`).
:mod:`~ciliary_carpet.stokes.reference`
    :func:`stokeslet_velocity_numpy`, the plain-numpy reference.
:mod:`~ciliary_carpet.stokes.treecode`
    :class:`Treecode`, repeated sums over fixed points as a linear operator and its transpose.
"""
from ciliary_carpet.stokes.backend import Backend
from ciliary_carpet.stokes.cuda import Cuda, CudaUnavailableError, cuda_available
from ciliary_carpet.stokes.direct import Direct, ranged_fp32
from ciliary_carpet.stokes.dispatch import (
    BACKENDS,
    Auto,
    backend_named,
    in_fp32,
    ranged_backend,
    stokeslet_velocity,
    stokeslet_velocity_ranges,
)
from ciliary_carpet.stokes.fmm import FMM, FMM_CROSSOVER_PAIRS
from ciliary_carpet.stokes.kernel import (
    C1_FREE,
    C1_WALL,
    C2_FREE,
    C2_WALL,
    C3_FREE,
    C3_WALL,
    KERNELS,
    Blake,
    Kernel,
    RegularisedBlake,
    RegularisedStokeslet,
    Stokeslet,
    Wall,
    make_kernel,
)
from ciliary_carpet.stokes.precision import fp32_error_bound, fp32_sources
from ciliary_carpet.stokes.reference import stokeslet_velocity_numpy
from ciliary_carpet.stokes.treecode import QUADRUPOLE, QUADRUPOLE_INV, Treecode

__all__ = [
    "Wall", "Kernel", "Stokeslet", "Blake", "RegularisedStokeslet", "RegularisedBlake", "KERNELS", "make_kernel",
    "C1_FREE", "C1_WALL", "C2_FREE", "C2_WALL", "C3_FREE", "C3_WALL",
    "Backend", "Direct", "FMM", "Cuda", "CudaUnavailableError", "cuda_available", "Auto", "BACKENDS",
    "backend_named", "ranged_backend", "in_fp32", "ranged_fp32", "fp32_sources", "fp32_error_bound",
    "FMM_CROSSOVER_PAIRS",
    "stokeslet_velocity", "stokeslet_velocity_ranges", "stokeslet_velocity_numpy", "Treecode", "QUADRUPOLE", "QUADRUPOLE_INV",
]
