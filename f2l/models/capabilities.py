"""Optional capabilities of a lighting model: typed mixins the estimator picks its strategy from.

A model declares a capability by inheriting its mixin next to :class:`~f2l.models.base.LightingModel`
(``class MySky(LightingModel, CompactSun)``) and filling in what the mixin asks for. The registry
checks each declared capability when it loads the class (layouts, abstract methods) and again,
numerically, the first time the model is made on a grid (:func:`check_model`); a model that
cannot honour what it declares is refused with a message naming the plugin and the capability.
``f2l models`` lists what each model declares; ``docs/plugins.md`` is the author's guide.

=============  ==========================  ===================================================
capability      mixin                       what the estimator does with it
=============  ==========================  ===================================================
linear          :class:`LinearRadiance`     T @ B precomputed once; closed-form / IRLS solves
sun-angles      :class:`SunAngles`          capture-time prior on the sun's elevation
compact-sun     :class:`CompactSun`         exact sun-core transport + global sun search (NNLS
                                            over every sun direction), weights as albedo x w
latent-sky      :class:`LatentSky`          batched (code x azimuth) start search through the
                                            block transport, L-BFGS on (code, azimuth, psi)
=============  ==========================  ===================================================

Without any, a model is estimated through a rank-k factor of T and L-BFGS from its
``initial_points()`` (the generic path: correct, but slower).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from f2l.lighting.grid import direction_from_angles

KAPPA_RANGE = (8.0, 8192.0)  # vMF concentrations the exact-core transport handles (1/rad^2)


class CapabilityError(TypeError):
    """A model declares a capability it does not honour (the message names both)."""


# -- linear ----------------------------------------------------------------------------------------
class LinearRadiance(ABC):
    """capability ``linear``: radiance(params) == B @ params.reshape(K, 3), B = ``linear_basis()``.

    The estimator precomputes T @ B once (each evaluation is then O(N K)); sphere-domain linear
    models are solved by IRLS in closed form (``f2l.estimate.linear``). Optional:
    ``prior_precision(theta)`` (K, 3) a diagonal precision majorising the prior (IRLS), and
    ``prior_nll_numpy(theta)`` (value, gradient) of the prior in numpy (the albedo split).
    """

    capability: ClassVar[str] = "linear"

    @abstractmethod
    def linear_basis(self) -> np.ndarray:
        """(L, K) basis on the flattened grid; the model has P = 3 K parameters (K x RGB)."""

    def prior_precision(self, theta: np.ndarray) -> np.ndarray | None:
        return None

    def prior_nll_numpy(self, theta: np.ndarray) -> tuple[float, np.ndarray] | None:
        return None


# -- sun angles --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SunAngleLayout:
    """Parameter indices of the sun's elevation (rad, 0 = horizon, pi/2 = zenith) and azimuth
    (rad, grid convention: 0 = -Z, the camera's view; +pi/2 = +X)."""

    elevation: int
    azimuth: int


class SunAngles(ABC):
    """capability ``sun-angles``: the sun's direction is two of the parameters.

    Declare ``sun_angles = SunAngleLayout(elevation=i, azimuth=j)``. The estimator can then put the
    capture-time prior (the sun's elevation from the photo's time and place) on parameter i, and
    ``sun_direction`` comes from the two angles unless the model overrides it.
    """

    capability: ClassVar[str] = "sun-angles"
    sun_angles: ClassVar[SunAngleLayout]

    def sun_direction(self, params: np.ndarray) -> np.ndarray | None:
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        lay = self.sun_angles
        return direction_from_angles(float(np.clip(p[lay.elevation], 0.0, 0.5 * math.pi)), float(p[lay.azimuth]))


# -- compact sun ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SunLayout(SunAngleLayout):
    """Parameter indices of a sun-plus-sky model (``CompactSun``): the sky's RGB weight, the
    sun's RGB irradiance at normal incidence, its angles, and its vMF concentration kappa
    (None: the model's fixed ``sun_kappa``)."""

    sky_rgb: tuple[int, int, int] = (0, 1, 2)
    sun_rgb: tuple[int, int, int] = (3, 4, 5)
    kappa: int | None = None


class CompactSun(SunAngles):
    """capability ``compact-sun``: radiance = w_sky ⊙ sky(params) + w_sun ⊙ vMF(sun, kappa).

    The model supplies ``sun_layout`` and ``sky(params)``, the unit-weight sky on the upper rows:
    it must not depend on the weights w_sky, w_sun (it may depend on the sun's angles and any other
    shape parameter). The sun is f2l's integrated vMF lobe (``f2l.lighting.sun_lobe``, unit energy,
    kappa in [8, 8192]). The mixin provides ``radiance`` and ``radiance_parts`` from these; in
    return the estimator gives the model
    - the exact-core sky transport (``f2l.estimate.sky_transport``): the lobe's texels see exact
      visibility, the smooth sky a block average, so hard cast shadows of the sun are kept;
    - the global sun search (``f2l.estimate.sun_search``): every sun direction on a ~5.6 deg
      lattice x each of ``search_shapes()`` scored by a per-channel NNLS in (w_sky, w_sun);
    - the fit in psi = albedo x weight, and the capture-time elevation prior (``sun-angles``).
    Domain must be ``"sky"``.
    """

    capability: ClassVar[str] = "compact-sun"
    sun_layout: ClassVar[SunLayout]
    sun_kappa: ClassVar[float] = 2048.0  # used when sun_layout.kappa is None

    @property
    def sun_angles(self) -> SunAngleLayout:  # type: ignore[override]
        return SunAngleLayout(self.sun_layout.elevation, self.sun_layout.azimuth)

    @abstractmethod
    def sky(self, params: torch.Tensor) -> torch.Tensor:
        """(B, P) -> (B, sky_rows * W, 3) unit-weight sky radiance on the upper rows (float64)."""

    def search_shapes(self) -> np.ndarray:
        """(S, P) sky shapes the sun search scores (their weights and sun are set by the search);
        default: the distinct ``initial_points()`` with unit grey sky and no sun."""
        lay = self.sun_layout
        shapes = np.array(self.initial_points(), dtype=np.float64)
        shapes[:, list(lay.sky_rgb)] = 1.0
        shapes[:, list(lay.sun_rgb)] = 0.0
        shapes[:, [lay.elevation, lay.azimuth]] = (0.5, 0.0)
        return np.unique(shapes, axis=0)

    def radiance_parts(self, params: torch.Tensor) -> tuple[torch.Tensor, tuple]:
        """(radiance (B, L, 3) float64, sun = (vals (B, K), flat (B, K), w_sun (B, 3))): the lobe's
        texel means on its window and flat indices (``sun_lobe_sparse``), for the exact core."""
        sky, w_sky, sun = self.light_parts(params)
        vals, flat, w_sun = sun
        upper = sky * w_sky[:, None, :]
        upper = upper.scatter_add_(1, flat[:, :, None].expand(-1, -1, 3), vals[:, :, None] * w_sun[:, None, :])
        out = torch.nn.functional.pad(upper, (0, 0, 0, self.grid.size - upper.shape[1]))
        return out, sun

    def light_parts(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple]:
        """The radiance's parts before they are added up: the unit-weight sky (B, sky_rows * W, 3)
        (float64, ``sky(params)``), w_sky (B, 3) and sun = (vals, flat, w_sun) as in
        :meth:`radiance_parts`, whose upper rows are w_sky ⊙ sky + the lobe scattered times w_sun.
        The estimator reads them apart: it needs the sky's block means, not its texels."""
        from f2l.lighting.sun_lobe import sun_lobe_sparse

        grid, lay = self.grid, self.sun_layout
        p = params.to(torch.float64)
        w_sky = p[:, list(lay.sky_rgb)].clamp_min(0.0)
        w_sun = p[:, list(lay.sun_rgb)].clamp_min(0.0)
        elevation = p[:, lay.elevation].clamp(0.0, 0.5 * math.pi)
        kappa = (p[:, lay.kappa] if lay.kappa is not None else torch.full_like(elevation, self.sun_kappa))
        kappa = kappa.clamp(*KAPPA_RANGE)
        vals, flat = sun_lobe_sparse(grid, 0.5 * math.pi - elevation, p[:, lay.azimuth], kappa, grid.sky_rows)
        return self.sky(p).to(torch.float64), w_sky, (vals, flat, w_sun)

    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        return self.radiance_parts(params)[0].to(params.dtype)


# -- latent sky -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LatentLayout:
    """Parameter indices of a latent-sky model: log exposure, the code (a slice), sun azimuth."""

    exposure: int
    code: slice
    azimuth: int


class LatentSky(ABC):
    """capability ``latent-sky``: radiance = e^{z_0} R(phi) D(code), a decoded sky, rotated.

    The model supplies ``latent_layout``, ``decode_sky(codes, azimuth)`` (unit exposure, on the
    grid's sky rows, channel-first, differentiable in both), ``search_codes()`` and
    ``code_prior_nll(codes)``. Rotating by an azimuth must roll the sky's columns (a whole
    column per 2 pi / W): the search scores every (code, azimuth) pair by rolling one decoded
    sky per code. The estimator (``f2l.estimate.latent``) then runs a batched start search through
    the block transport and L-BFGS on (code, azimuth, albedo x exposure). Domain must be ``"sky"``.
    """

    capability: ClassVar[str] = "latent-sky"
    latent_layout: ClassVar[LatentLayout]

    @abstractmethod
    def decode_sky(self, codes: torch.Tensor, azimuth: torch.Tensor | None) -> torch.Tensor:
        """(B, D) codes, (B,) azimuths or None -> (B, 3, sky_rows, W) unit-exposure sky (float32)."""

    @abstractmethod
    def search_codes(self) -> np.ndarray:
        """(K, D) codes the start search decodes once and scores at every azimuth."""

    def code_prior_nll(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B,) prior negative log-likelihood of the codes (default 0)."""
        return torch.zeros(codes.shape[0], dtype=codes.dtype)

    @property
    def cache_key(self) -> tuple:
        """What the decoded search skies may be cached by, per process (e.g. the weights file)."""
        return (type(self).__module__, type(self).__qualname__, id(self))


@contextmanager
def single_thread():
    """torch with one intra-op thread inside the block (restored after): for values a model caches
    once per process (decoded search skies, encoded codes), which must not depend on the thread
    count whoever ran before left behind (float32 kernels round differently per thread count)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


CAPABILITIES: tuple[type, ...] = (LinearRadiance, CompactSun, SunAngles, LatentSky)


def declared(cls_or_model) -> list[str]:
    """Names of the capabilities a model class (or instance) declares, most specific first."""
    cls = cls_or_model if isinstance(cls_or_model, type) else type(cls_or_model)
    return [c.capability for c in CAPABILITIES if issubclass(cls, c)]


# -- registration checks -----------------------------------------------------------------------------------
def check_class(cls: type) -> None:
    """Static checks of the declared capabilities (no instance): layouts of the right type."""
    if issubclass(cls, CompactSun):
        lay = getattr(cls, "sun_layout", None)
        if not isinstance(lay, SunLayout):
            raise CapabilityError(_msg(cls, "compact-sun", "sun_layout must be a f2l.models.capabilities.SunLayout"))
        indices = [*lay.sky_rgb, *lay.sun_rgb, lay.elevation, lay.azimuth] + ([lay.kappa] if lay.kappa is not None else [])
        if len(set(indices)) != len(indices):
            raise CapabilityError(_msg(cls, "compact-sun", f"sun_layout indices overlap: {indices}"))
        if not KAPPA_RANGE[0] <= float(cls.sun_kappa) <= KAPPA_RANGE[1]:
            raise CapabilityError(_msg(cls, "compact-sun", f"sun_kappa {cls.sun_kappa} outside {KAPPA_RANGE}"))
    elif issubclass(cls, SunAngles) and not isinstance(getattr(cls, "sun_angles", None), SunAngleLayout):
        raise CapabilityError(_msg(cls, "sun-angles", "sun_angles must be a f2l.models.capabilities.SunAngleLayout"))
    if issubclass(cls, LatentSky) and not isinstance(getattr(cls, "latent_layout", None), LatentLayout):
        raise CapabilityError(_msg(cls, "latent-sky", "latent_layout must be a f2l.models.capabilities.LatentLayout"))
    if issubclass(cls, (CompactSun, LatentSky)) and getattr(cls, "domain", "sky") != "sky":
        raise CapabilityError(_msg(cls, declared(cls)[0], "the capability needs domain = 'sky'"))


def check_model(model) -> None:
    """Numerical checks of the declared capabilities on the model's own grid: what the estimator
    will rely on holds. Raises :class:`CapabilityError` naming the capability and what failed
    (also when the model's own code raises while being checked)."""
    checks = [(LinearRadiance, "linear", _check_linear), (SunAngles, "sun-angles", _check_sun_angles),
              (CompactSun, "compact-sun", _check_compact_sun), (LatentSky, "latent-sky", _check_latent_sky)]
    for mixin, name, check in checks:
        if not isinstance(model, mixin):
            continue
        try:
            with torch.no_grad():
                check(model)
        except CapabilityError:
            raise
        except Exception as exc:  # noqa: BLE001 - a plugin's own error, reported with its capability
            raise CapabilityError(_msg(type(model), name, f"checking it raised {type(exc).__name__}: {exc}")) from exc


def _check_linear(model: LinearRadiance) -> None:
    cls, P = type(model), model.num_params
    basis = np.asarray(model.linear_basis(), dtype=np.float64)
    if basis.ndim != 2 or basis.shape[0] != model.grid.size or 3 * basis.shape[1] != P:
        raise CapabilityError(_msg(cls, "linear", f"linear_basis() has shape {basis.shape}; expected "
                                                  f"({model.grid.size}, {P // 3}) for {P} parameters"))
    theta = np.random.default_rng(0).standard_normal(P)
    rad = model.radiance(torch.as_tensor(theta)[None])[0].numpy()
    want = basis @ theta.reshape(-1, 3)
    if not np.allclose(rad, want, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(want).max())):
        raise CapabilityError(_msg(cls, "linear", "radiance(params) differs from linear_basis() @ params"))


def _check_sun_angles(model: SunAngles) -> None:
    lay, P = model.sun_angles, model.num_params
    for what, i in (("elevation", lay.elevation), ("azimuth", lay.azimuth)):
        if not 0 <= i < P:
            raise CapabilityError(_msg(type(model), "sun-angles", f"{what} index {i} outside the {P} parameters"))


def _check_compact_sun(model: CompactSun) -> None:
    cls, lay, grid = type(model), model.sun_layout, model.grid
    P = model.num_params
    bad = [i for i in (*lay.sky_rgb, *lay.sun_rgb, lay.kappa) if i is not None and not 0 <= i < P]
    if bad:
        raise CapabilityError(_msg(cls, "compact-sun", f"sun_layout indices {bad} outside the {P} parameters"))
    starts = np.atleast_2d(np.asarray(model.initial_points(), dtype=np.float64))
    p = torch.as_tensor(starts[: min(4, len(starts))])
    sky = model.sky(p)
    want = (p.shape[0], grid.sky_rows * grid.width, 3)
    if tuple(sky.shape) != want:
        raise CapabilityError(_msg(cls, "compact-sun", f"sky(params) has shape {tuple(sky.shape)}; expected {want}"))
    sky = sky.to(torch.float64)
    if not torch.isfinite(sky).all() or (sky < 0).any():
        raise CapabilityError(_msg(cls, "compact-sun", "sky(params) is negative or not finite"))
    moved = p.clone()
    moved[:, list(lay.sky_rgb) + list(lay.sun_rgb)] = moved[:, list(lay.sky_rgb) + list(lay.sun_rgb)] * 2.0 + 0.5
    if not torch.allclose(model.sky(moved).to(torch.float64), sky, rtol=1e-6, atol=1e-9 * float(sky.abs().max())):
        raise CapabilityError(_msg(cls, "compact-sun", "sky(params) depends on the weights w_sky / w_sun "
                                                       "(it must be the unit-weight sky)"))
    if type(model).radiance is not CompactSun.radiance:  # an own radiance must agree with the parts
        own = model.radiance(p).to(torch.float64)
        parts = CompactSun.radiance_parts(model, p)[0]
        if not torch.allclose(own, parts, rtol=1e-4, atol=1e-6 * float(parts.abs().max())):
            raise CapabilityError(_msg(cls, "compact-sun", "radiance(params) differs from w_sky * sky(params) + "
                                                           "w_sun * vMF lobe (f2l.lighting.sun_lobe)"))
    shapes = np.atleast_2d(np.asarray(model.search_shapes(), dtype=np.float64))
    if shapes.ndim != 2 or shapes.shape[1] != P or len(shapes) == 0:
        raise CapabilityError(_msg(cls, "compact-sun", f"search_shapes() has shape {shapes.shape}; expected (S, {P})"))


def _check_latent_sky(model: LatentSky) -> None:
    cls, lay, grid = type(model), model.latent_layout, model.grid
    P = model.num_params
    code_dim = len(range(P)[lay.code])
    if not (0 <= lay.exposure < P and 0 <= lay.azimuth < P and code_dim > 0):
        raise CapabilityError(_msg(cls, "latent-sky", f"latent_layout {lay} does not fit the {P} parameters"))
    codes = np.atleast_2d(np.asarray(model.search_codes(), dtype=np.float64))
    if codes.shape[1] != code_dim:
        raise CapabilityError(_msg(cls, "latent-sky", f"search_codes() has width {codes.shape[1]}; the code has "
                                                      f"{code_dim} entries"))
    z = torch.as_tensor(codes[:1], dtype=torch.float32)
    sky = model.decode_sky(z, None)
    want = (1, 3, grid.sky_rows, grid.width)
    if tuple(sky.shape) != want:
        raise CapabilityError(_msg(cls, "latent-sky", f"decode_sky has shape {tuple(sky.shape)}; expected {want}"))
    if not torch.isfinite(sky).all() or (sky < 0).any():
        raise CapabilityError(_msg(cls, "latent-sky", "decode_sky is negative or not finite"))
    k = max(1, grid.width // 8)
    turned = model.decode_sky(z, torch.tensor([2.0 * math.pi * k / grid.width], dtype=torch.float32))
    scale = float(sky.abs().max())
    if not torch.allclose(turned, torch.roll(sky, k, dims=-1), rtol=1e-3, atol=1e-4 * scale):
        raise CapabilityError(_msg(cls, "latent-sky", f"rotating by 2 pi {k}/{grid.width} does not roll the sky by "
                                                      f"{k} columns"))


def _msg(cls: type, capability: str, what: str) -> str:
    return f"{cls.__module__}:{cls.__qualname__} declares capability {capability!r}, but {what}"
