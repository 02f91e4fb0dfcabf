"""Optics of a ray at an interface: reflection, refraction, Fresnel, dispersion.

    r = reflect(l, n)                       # seed, eq. (2)
    t, tir = refract(l, n, n1, n2)          # seed, eq. (1)
    n_facing, entering = orient(l, n)
    n1, n2 = interface_indices(entering, n_inside, n_outside)
    R, T = fresnel(cos_i, n1, n2)           # unpolarised power coefficients
    n = glass_index("BK7", wavelength_nm)   # Cauchy, n(λ) = A + B/λ² (seed)

Conventions (the seed's, Proposition 3.2): ``l`` is the unit direction of the incident ray,
``n`` the unit normal on the side the ray comes from, so that ``l · n < 0`` and
``cos i1 = -l · n >= 0``. ``n1`` is the index of the medium the ray comes from, ``n2`` that
of the medium it enters. Angles are in radians, wavelengths in nm, Cauchy's B in µm².

Everything here is pure JAX and broadcasts: vectors carry their three coordinates on the
last axis, indices and cosines broadcast against the leading axes. The array functions are
wrapped in ``jax.jit`` (one fused kernel per call, also inside other jitted code) and check
no values; the catalogue look-ups, which take Python strings, check their names. Results
are float32 unless an argument is float64 (with ``jax_enable_x64``): Python numbers do not
widen the result. Nothing returns NaN for unit inputs: square roots are taken of
``max(x, 0)`` and every quotient is guarded.

Precision: near the critical angle R has an infinite slope (cos i2 ~ sqrt(i_c - i1)), so no
float32 evaluation can be accurate there in absolute terms; :func:`fresnel` returns the
exact R of a cosine within a few ulps of the one given (tests/test_optics.py). Likewise a
ray refracted at grazing incidence (cos i1 below ~1e-2) into a denser medium carries its
angle in float32 only to about n² ε / cos i1: leaving through a parallel face, it may come
out that far from parallel, or, for cos i1 of order sqrt(ε), be caught by total internal
reflection. Pass float64 where that matters.

Dot products are written out component by component, as in :mod:`jrt.kernels`, so that no
backend runs them as reduced-precision matmuls.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

Vec = Float[Array, "*batch 3"]
Scalar = Float[Array, "*batch"]
Index = Float[Array, "*batch"] | float
Mask = Bool[Array, "*batch"]


def _dtype(*args):
    """float32 unless an argument is float64: Python scalars are weak and do not widen."""
    return jnp.result_type(*args, jnp.float32)


def _dot(a: Vec, b: Vec) -> Scalar:
    """a · b over the last axis, written out (see the module docstring)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


@jax.custom_jvp
def _safe_sqrt(x):
    """sqrt(max(x, 0)): never NaN, also for a radicand that rounding pushed below zero.

    Its derivative, 1 / (2 sqrt(x)), is infinite at 0 (the critical angle, where R has an
    infinite slope) and 0 below: it is bounded by :data:`MAX_SQRT_SLOPE`, so that the
    tangent of a ray at the critical angle stays finite and a reverse-mode gradient never
    multiplies an infinity by a zero (which would be NaN)."""
    return jnp.sqrt(jnp.maximum(x, 0))


#: The largest derivative of :func:`_safe_sqrt` (that of sqrt at x = 2.5e-13): a
#: radicand within 2^-42 of the critical angle's zero, of no geometric meaning in float32.
MAX_SQRT_SLOPE = 1e6


@_safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x,), (x_dot,) = primals, tangents
    root = jnp.sqrt(jnp.maximum(x, 0))
    slope = jnp.where(x > 0, jnp.minimum(0.5 / jnp.maximum(root, 1e-30), MAX_SQRT_SLOPE), 0)
    return root, slope * x_dot


def _cos_transmitted(cos_i, n1, n2):
    """(cos i2, tir) from Snell–Descartes, n1 sin i1 = n2 sin i2 (seed, "Snell-Descartes (2)").

    cos² i2 = 1 - (n1/n2)² (1 - cos² i1) (seed, eq. 1's radicand; pbrt-v4 §9.3.4,
    ``Refract``), evaluated as ((n2 - n1)(n2 + n1) + (n1 cos i1)²) / n2²: the same number,
    but n2 - n1 is exact in floating point for close indices (Sterbenz), where the
    textbook order loses most digits to 1 - (n1/n2)², and 1 - cos² i1 never appears.
    Total internal reflection where this radicand is negative (Born & Wolf §1.5.4); there
    ``cos i2`` is returned as 0, the limit at the critical angle.
    """
    a = n1 * cos_i
    k = ((n2 - n1) * (n2 + n1) + a * a) / (n2 * n2)
    return _safe_sqrt(k), k < 0


# --- Directions -----------------------------------------------------------------------------


@jax.jit
def reflect(l: Vec, n: Vec) -> Vec:
    """Reflected direction: r = l + 2 cos(i1) n, cos(i1) = -l · n (seed, eq. 2).

    ``l`` unit incident direction, ``n`` unit normal with ``l · n < 0``. The result is a unit
    vector in the plane of ``l`` and ``n`` with the angle of reflection equal to the angle of
    incidence (seed, "Snell-Descartes (3)": i1 = -i'1). The formula is the mirror image
    ``l - 2 (l · n) n``, so it also holds (unchanged) for a normal on the other side.
    """
    l = jnp.asarray(l)
    n = jnp.asarray(n)
    dtype = _dtype(l, n)
    l, n = l.astype(dtype), n.astype(dtype)
    cos_i = -_dot(l, n)
    return l + (2 * cos_i)[..., None] * n


@jax.jit
def refract(l: Vec, n: Vec, n1: Index, n2: Index) -> tuple[Vec, Mask]:
    """Refracted direction and the total-internal-reflection mask (seed, eq. 1).

        t = (n1/n2) l + ((n1/n2) cos i1 - cos i2) n,
        cos i1 = -l · n,   cos i2 = sqrt(1 - (n1/n2)² (1 - cos² i1)).

    ``l`` unit incident direction [..., 3]; ``n`` unit normal facing the incoming ray
    (``l · n < 0``, see :func:`orient`); ``n1`` the index on the ray's side, ``n2`` the index
    beyond the interface (scalars or arrays broadcasting with the leading axes).

    Returns ``(t, tir)``. ``tir`` is True where the radicand is negative: total internal
    reflection, past the critical angle asin(n2/n1) (Born & Wolf §1.5.4). There ``t`` is the
    reflected direction :func:`reflect` (seed, eq. 2), which is where all the light goes;
    it is finite and unit, never NaN. Elsewhere ``t`` is a unit vector in the plane of
    ``l`` and ``n`` with n1 sin i1 = n2 sin i2 (seed, "Snell-Descartes (1)-(2)").
    """
    l = jnp.asarray(l)
    n = jnp.asarray(n)
    dtype = _dtype(l, n, n1, n2)
    l, n = l.astype(dtype), n.astype(dtype)
    n1 = jnp.asarray(n1, dtype)
    n2 = jnp.asarray(n2, dtype)
    cos_i = jnp.clip(-_dot(l, n), -1, 1)
    eta = n1 / n2
    cos_t, tir = _cos_transmitted(cos_i, n1, n2)
    eta, cos_t, tir = jnp.broadcast_arrays(eta, cos_t, tir)
    # Seed, eq. (1); pbrt-v4 §9.3.4 (``Refract``) writes the same vector.
    t = eta[..., None] * l + (eta * cos_i - cos_t)[..., None] * n
    r = l + (2 * cos_i)[..., None] * n  # seed, eq. (2)
    return jnp.where(tir[..., None], r, t), tir


@jax.jit
def orient(l: Vec, n: Vec) -> tuple[Vec, Mask]:
    """Turn a normal to face the incoming ray; tell entering from leaving.

    ``n`` is the outward normal of a closed surface (geometric or shading). A ray with
    ``l · n < 0`` comes from outside: it is entering the medium (seed, Proposition 3.2,
    takes the normal on the incident side). With ``l · n >= 0`` it is leaving, and the
    normal is flipped. Returns ``(n_facing, entering)`` with ``l · n_facing <= 0``: the
    normal :func:`reflect` and :func:`refract` expect (pbrt-v4 §3.5, ``FaceForward``).
    """
    l = jnp.asarray(l)
    n = jnp.asarray(n)
    dtype = _dtype(l, n)
    l, n = l.astype(dtype), n.astype(dtype)
    entering = _dot(l, n) < 0
    return jnp.where(entering[..., None], n, -n), entering


@jax.jit
def interface_indices(
    entering: Mask, n_inside: Index, n_outside: Index = 1.0
) -> tuple[Scalar, Scalar]:
    """(n1, n2) at an interface: from outside in when ``entering``, from inside out else.

    ``n1`` is the index of the medium the ray comes from, ``n2`` that of the medium it
    enters, as in the seed's Snell–Descartes laws.
    """
    dtype = _dtype(n_inside, n_outside)
    n_inside = jnp.asarray(n_inside, dtype)
    n_outside = jnp.asarray(n_outside, dtype)
    n1 = jnp.where(entering, n_outside, n_inside)
    n2 = jnp.where(entering, n_inside, n_outside)
    return n1, n2


# --- Power coefficients ---------------------------------------------------------------------


def _ratio_squared(num, den):
    """(num/den)², and 1 where den = 0: the only such case is grazing incidence under
    total internal reflection (cos i1 = cos i2 = 0), where every reflectance is 1."""
    ok = den > 0
    q = num / jnp.where(ok, den, 1)
    return jnp.where(ok, q * q, 1)


@jax.jit
def fresnel_sp(cos_i: Scalar, n1: Index, n2: Index) -> tuple[Scalar, Scalar]:
    """Fresnel reflectances (Rs, Rp) of a dielectric interface, for s and p polarisation.

        rs = (n1 cos i1 - n2 cos i2) / (n1 cos i1 + n2 cos i2),
        rp = (n2 cos i1 - n1 cos i2) / (n2 cos i1 + n1 cos i2),     Rs = rs², Rp = rp²

    (Born & Wolf §1.5.2; Hecht §4.6.2, eqs. 4.34 and 4.40; pbrt-v4 §9.3.5).
    ``cos_i`` in [0, 1] is the cosine of the angle of incidence in medium ``n1`` (values
    outside are clipped). Under total internal reflection both are 1 (Born & Wolf §1.5.4:
    |rs| = |rp| = 1); as the critical angle is approached from below cos i2 -> 0 and both
    tend to 1, so R is continuous there. Rp = 0 at Brewster's angle, atan(n2/n1).
    """
    dtype = _dtype(cos_i, n1, n2)
    cos_i = jnp.clip(jnp.asarray(cos_i, dtype), 0, 1)
    n1 = jnp.asarray(n1, dtype)
    n2 = jnp.asarray(n2, dtype)
    cos_t, tir = _cos_transmitted(cos_i, n1, n2)
    rs2 = _ratio_squared(n1 * cos_i - n2 * cos_t, n1 * cos_i + n2 * cos_t)
    rp2 = _ratio_squared(n2 * cos_i - n1 * cos_t, n2 * cos_i + n1 * cos_t)
    one = jnp.ones_like(rs2)
    return jnp.where(tir, one, rs2), jnp.where(tir, one, rp2)


@jax.jit
def fresnel(cos_i: Scalar, n1: Index, n2: Index) -> tuple[Scalar, Scalar]:
    """Unpolarised Fresnel power coefficients (R, T): R = (Rs + Rp)/2, T = 1 - R.

    Natural light carries equal power in both polarisations (Hecht §4.6.3;
    pbrt-v4 §9.3.5, ``FrDielectric``). T = 1 - R: no absorption at the interface (seed,
    Remarque 3.5, R + T = 1). R = 1 and T = 0 under total internal reflection. At normal
    incidence this is :func:`fresnel_normal`.
    """
    rs, rp = fresnel_sp(cos_i, n1, n2)
    r = 0.5 * (rs + rp)
    return r, 1 - r


@jax.jit
def fresnel_normal(n1: Index, n2: Index) -> tuple[Scalar, Scalar]:
    """The seed's normal-incidence coefficients ("La puissance au service de la couleur"):

        R = ((n1 - n2) / (n1 + n2))²,   T = 4 n1 n2 / (n1 + n2)².
    """
    dtype = _dtype(n1, n2)
    n1 = jnp.asarray(n1, dtype)
    n2 = jnp.asarray(n2, dtype)
    s = n1 + n2
    d = (n1 - n2) / s
    return d * d, 4 * n1 * n2 / (s * s)


@jax.jit
def schlick(cos_i: Scalar, n1: Index, n2: Index) -> tuple[Scalar, Scalar]:
    """Schlick's approximation of the unpolarised R (Schlick, Computer Graphics
    Forum 13(3), 1994), an ablation.

        R = R0 + (1 - R0) (1 - c)^5,   R0 = ((n1 - n2) / (n1 + n2))²  (seed's normal R).

    ``c`` is cos i1 when n1 <= n2. When n1 > n2 the angle in the denser medium is the wrong
    one to use (R would not reach 1 at the critical angle): ``c`` is then cos i2, the cosine
    on the rarer side (Fresnel's R is symmetric under swapping the two sides, Stokes
    relations, Hecht §4.10), and R = 1 under total internal reflection. T = 1 - R.
    """
    dtype = _dtype(cos_i, n1, n2)
    cos_i = jnp.clip(jnp.asarray(cos_i, dtype), 0, 1)
    n1 = jnp.asarray(n1, dtype)
    n2 = jnp.asarray(n2, dtype)
    r0, _ = fresnel_normal(n1, n2)
    cos_t, tir = _cos_transmitted(cos_i, n1, n2)
    c = jnp.where(n1 > n2, cos_t, cos_i)
    m = 1 - c
    m2 = m * m
    r = r0 + (1 - r0) * (m2 * m2 * m)
    r = jnp.where(tir, jnp.ones_like(r), r)
    return r, 1 - r


# --- Dispersion -----------------------------------------------------------------------------


@jax.jit
def cauchy(A: Index, B: Index, wavelength_nm: Scalar) -> Scalar:
    """Cauchy's law n(λ) = A + B / λ² (seed, "La puissance au service de la couleur").

    ``B`` in µm², ``wavelength_nm`` the vacuum wavelength in nm (converted to µm).
    """
    dtype = _dtype(A, B, wavelength_nm)
    lam_um = jnp.asarray(wavelength_nm, dtype) * 1e-3
    return jnp.asarray(A, dtype) + jnp.asarray(B, dtype) / (lam_um * lam_um)


@jax.jit
def sellmeier(
    B1: float, B2: float, B3: float, C1: float, C2: float, C3: float, wavelength_nm: Scalar
) -> Scalar:
    """Three-term Sellmeier formula, n² = 1 + Σ Bi λ² / (λ² - Ci), Ci in µm², λ in nm.

    The form of the Schott catalogue ("Sellmeier 1", Schott TIE-29) and of Malitson 1965
    (whose Ci are quoted as resonance wavelengths, squared here).
    """
    dtype = _dtype(wavelength_nm, B1, C1)
    lam_um = jnp.asarray(wavelength_nm, dtype) * 1e-3
    l2 = lam_um * lam_um
    n2 = 1 + B1 * l2 / (l2 - C1) + B2 * l2 / (l2 - C2) + B3 * l2 / (l2 - C3)
    return jnp.sqrt(n2)


#: Published Sellmeier coefficients (B1, B2, B3, C1, C2, C3), C in µm², as quoted by
#: refractiveindex.info: fused silica from Malitson, JOSA 55, 1205 (1965) (Ci = λi², with
#: λi = 0.0684043, 0.1162414, 9.896161 µm); the others from the Schott optical glass
#: catalogue (data sheets of N-BK7, N-K5, N-BAK4, N-BAF10 and SF10).
SELLMEIER: dict[str, tuple[float, float, float, float, float, float]] = {
    "fused silica": (0.6961663, 0.4079426, 0.8974794, 0.0684043**2, 0.1162414**2, 9.896161**2),
    "BK7": (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
    "K5": (1.08511833, 0.199562005, 0.930511663, 0.00661099503, 0.024110866, 111.982777),
    "BaK4": (1.28834642, 0.132817724, 0.945395373, 0.00779980626, 0.0315631177, 105.965875),
    "BaF10": (1.5851495, 0.143559385, 1.08521269, 0.00926681282, 0.0424489805, 105.613573),
    "SF10": (1.61625977, 0.259229334, 1.07762317, 0.0127534559, 0.0581983954, 116.60768),
}

#: Cauchy coefficients (A, B in µm²) for n(λ) = A + B/λ², fitted once, offline, to the
#: Sellmeier curves above: ordinary least squares of n against (1, 1/λ²) over 301 vacuum
#: wavelengths evenly spaced from 400 to 700 nm (numpy.linalg.lstsq, float64), then A
#: rounded to 5 and B to 6 decimals. Largest deviation from the Sellmeier index over
#: 400-700 nm: fused silica 1.2e-4, BK7 1.0e-4, K5 8.3e-5, BaK4 1.7e-4, BaF10 5.0e-4,
#: SF10 2.4e-3 (a dense flint bends more than two terms can follow). The often-quoted
#: table (Wikipedia, "Cauchy's equation") gives BK7 (1.5046, 0.00420), the same fit; its
#: other rows do not reproduce their glasses' n_d (fused silica: 1.4580 + 0.00354/0.5876²
#: = 1.4683, against 1.4585) and are not used.
GLASSES: dict[str, tuple[float, float]] = {
    "fused silica": (1.44826, 0.003506),
    "BK7": (1.50459, 0.004202),
    "K5": (1.50910, 0.004615),
    "BaK4": (1.55328, 0.005360),
    "BaF10": (1.64806, 0.007588),
    "SF10": (1.68746, 0.014139),
}

#: Fraunhofer lines (nm) of the Abbe number: d (helium, 587.5618), F (hydrogen, 486.1327),
#: C (hydrogen, 656.2725) (Schott TIE-29).
FRAUNHOFER_NM: dict[str, float] = {"d": 587.5618, "F": 486.1327, "C": 656.2725}


def _check_glass(name: str, catalogue: dict) -> None:
    if name not in catalogue:
        allowed = ", ".join(repr(k) for k in catalogue)
        raise ValueError(f"unknown glass {name!r}: the catalogue has {allowed}")


def glass_index(name: str, wavelength_nm: Scalar) -> Scalar:
    """Index of a catalogue glass at ``wavelength_nm`` (nm), by Cauchy's law with
    :data:`GLASSES`. Raises ``ValueError`` naming an unknown glass and the allowed names."""
    _check_glass(name, GLASSES)
    A, B = GLASSES[name]
    return cauchy(A, B, wavelength_nm)


def abbe_number(name: str, model: str = "cauchy") -> float:
    """Abbe number V_d = (n_d - 1) / (n_F - n_C) of a catalogue glass (Schott TIE-29).

    ``model="cauchy"`` uses the Cauchy fit (what a render sees), ``"sellmeier"`` the
    published Sellmeier coefficients. Evaluated in float64 with NumPy, outside any jit.
    """
    if model not in ("cauchy", "sellmeier"):
        raise ValueError(f"unknown model {model!r}: use 'cauchy' or 'sellmeier'")
    catalogue = GLASSES if model == "cauchy" else SELLMEIER
    _check_glass(name, catalogue)
    lam_um = np.array([FRAUNHOFER_NM[k] for k in "dFC"]) * 1e-3
    l2 = lam_um * lam_um
    if model == "cauchy":
        A, B = GLASSES[name]
        nd, nF, nC = A + B / l2
    else:
        B1, B2, B3, C1, C2, C3 = SELLMEIER[name]
        nd, nF, nC = np.sqrt(1 + B1 * l2 / (l2 - C1) + B2 * l2 / (l2 - C2) + B3 * l2 / (l2 - C3))
    return float((nd - 1) / (nF - nC))
