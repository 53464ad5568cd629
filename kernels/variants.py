"""Precision and tolerance variants of the root solver and the narrow-phase CCD, generated from
the one implementation.

:mod:`kernels.roots` and the narrow phase (:mod:`kernels.ccd` with :mod:`kernels.ccd_common`,
:mod:`kernels.point_triangle`, :mod:`kernels.edge_edge`) are written once, in Warp float64, with
their precision-dependent numbers as literals and module constants. A *variant* is the same
source with

* the precision switched (``float32``): every ``wp.float64`` becomes ``wp.float32`` and every
  float64 vector / matrix type its float32 twin (``wp.vec3d`` -> ``wp.vec3f`` ...; the local
  ``vec6d``/``mat83d``/... aliases keep their names and get ``dtype=wp.float32``), and each
  constant of :data:`FLOAT32_CONSTANTS` replaced by its float32 value (below, with the reason);
* knobs set: the Newton-bisection iteration cap ``NEWTON_MAX_ITERATIONS`` (``max_iterations``),
  its relative step tolerance ``NEWTON_RELATIVE_TOLERANCE`` (``tolerance``), and the CCD's
  ``tolerance_scale``, a multiplier on ``COEFFICIENT_ERROR_FACTOR`` (64) and
  ``DISTANCE_ERROR_FACTOR`` (256), i.e. on the error bounds of the cubic's coefficients and of
  the distances that decide a hit (``< 1``: tighter, fewer false positives, risk of false
  negatives; ``> 1``: looser).

It is produced by text substitution of the modules' source (every pattern must occur exactly the
expected number of times, so an edit of the kernels that a substitution no longer matches fails
loudly instead of giving a silently wrong float32 variant), written as a private package
``tunnelsim_kv_<precision>_<hash>`` (hash of the sources, the settings and
:data:`GENERATOR_VERSION`) under ``<Warp kernel cache>/tunnelsim_variants/`` (Warp compiles from
real files: it reads the functions with ``inspect.getsource``) and imported with its
``from kernels.X import`` lines pointed at its own modules. Every file is written to a temporary
file and ``os.replace``-d, so processes generating the same variant at once (pytest-xdist) never
see a partial file; the content for a given name is deterministic. After the float32 rewrite any
float literal left outside float32's normal range is an error.

The default settings (float64, the kernels' own constants) return the original modules, so the
simulator never runs generated code: :func:`kernel_variant` with defaults is a dict lookup.

Variants are compiled forward-only (``enable_backward = False`` for their Warp modules): they
exist to measure the forward solver and narrow phase, and skipping the adjoint code cuts their
first compilation from ~9 s to ~4 s (roots) and from ~22 s to ~7 s (CCD) on one core. Gradients
(the mollified adjoints under a ``wp.Tape``) stay with the float64 originals.

Float32 constants (:data:`FLOAT32_CONSTANTS`; u32 = 2^-24, u64 = 2^-53):

========================================== ===================== ======================
constant (module)                          float64               float32
========================================== ===================== ======================
``DEFAULT_T_MAX`` / ``CCD_T_MAX``          1e150                 float32(1e18)
``NEWTON_RELATIVE_TOLERANCE`` (default)    2^-51 (2 ulp)         2^-22 (2 ulp)
``NO_RESCALE_MAX``                         2^100                 2^16
``bracket_split`` jump floor               1e-280 (~2^-930)      2^-80
``BALANCE_SPREAD``                         2^-960                2^-100
``scaled_root_limit`` range                2^+-1000              2^+-120
``SMALL_ARGUMENT``                         2^-100                2^-16
``quadratic_solve_scaled`` k range         [2^-200, 2^200]       [2^-32, 2^32]
deflation score sentinels                  -1e300, -1e299        -1e38, -1e37
``cubic_root_jacobian`` clamp cap        1e300                 1e30
``UNIT_ROUNDOFF``                          2^-53                 2^-24
``COPLANAR_RELATIVE``                      1e-12 (~9000 u64)     2^-16 (256 u32)
point-triangle degenerate test             1e-30 ((9 u64)^2)     2.88e-13 ((9 u32)^2)
``ccd_query`` inf                          1e308 * 10            3e38 * 10
========================================== ===================== ======================

The edge-edge parallel guard ``den > 1e-24 a c`` is kept: it only guards the division of the
line-line closest points, and any (s, t) it lets through is a real pair of points of the two
segments (checked to lie in [0, 1]^2), so a smaller threshold can only lower the distance
towards the true one; 1e-24 is a normal float32.

Example:
    >>> from kernels.variants import kernel_variant
    >>> v = kernel_variant("float32")                # generated (compiled by Warp on first launch)
    >>> v.roots.solve_cubic_kernel, v.ccd.ccd_kernel  # same names as kernels.roots / kernels.ccd
    >>> kernel_variant().roots is kernels.roots        # defaults: the original modules
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import io
import math
import operator
import os
import re
import sys
import tempfile
import threading
import tokenize
from dataclasses import dataclass
from pathlib import Path

GENERATOR_VERSION = "2"
"""Part of the variant hash: bump when the substitution rules change."""

PRECISIONS = ("float64", "float32")

MODULES = ("roots", "ccd_common", "point_triangle", "edge_edge", "ccd")
"""The modules of a variant, in import order (each imports only earlier ones)."""

DEFAULT_MAX_ITERATIONS = 256
"""``NEWTON_MAX_ITERATIONS`` of :mod:`kernels.roots` (checked against the source)."""

DEFAULT_TOLERANCE = {"float64": 2.0**-51, "float32": 2.0**-22}
"""``NEWTON_RELATIVE_TOLERANCE``: 2 ulp of 1 in the precision (float64 value checked against the source)."""

T_MAX = {"float64": 1.0e150, "float32": 9.999999843067494e17}
"""Root clamp ``t_max`` of the solver and the CCD (``DEFAULT_T_MAX``, ``CCD_T_MAX``).

float32: float32(1e18) (the float nearest 1e18, so a clamped root equals it exactly). The root
Jacobians form ``|t|^2`` of a clamped root (``n = at * at``), so ``t_max^2`` must be finite:
1e36, about 340x below FLT_MAX (float64: 1e300, 1.8e8 below DBL_MAX); 1e30 would overflow
there. Roots this large are far outside any CCD step [0, 1] anyway."""

UNIT_ROUNDOFF = {"float64": 2.0**-53, "float32": 2.0**-24}

_FLT_MAX = 3.4028234663852886e38
_FLT_MIN_NORMAL = 2.0**-126
_KERNELS_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Settings:
    """Normalised settings of a variant (see :func:`kernel_variant`)."""

    precision: str = "float64"
    max_iterations: int = DEFAULT_MAX_ITERATIONS
    tolerance: float = DEFAULT_TOLERANCE["float64"]
    tolerance_scale: float = 1.0

    @property
    def is_default(self) -> bool:
        return self == Settings()


@dataclass(frozen=True)
class Constant:
    """One substitution: ``old`` (exact source text, ``count`` occurrences in ``module``) becomes
    ``new`` with ``{value}`` replaced by ``repr(value(settings))``."""

    module: str
    old: str
    new: str
    value: object  # callable(Settings) -> number
    count: int
    why: str


def _f32(v):
    return lambda s: v


FLOAT32_CONSTANTS = (
    Constant("roots", "DEFAULT_T_MAX = 1.0e150", "DEFAULT_T_MAX = {value}", _f32(T_MAX["float32"]), 1,
             "t_max: t_max^2 must stay finite in the root Jacobians (1e36 < FLT_MAX = 3.4e38)"),
    Constant("roots", "NO_RESCALE_MAX = wp.constant(wp.float64(1.2676506002282294e30))",
             "NO_RESCALE_MAX = wp.constant(wp.float64({value}))", _f32(2.0**16), 1,
             "2^100 -> 2^16: the critical-point discriminant squares coefficients (2^200 overflows float32); "
             "about the same fraction of the exponent range (100/1024 ~ 12.5/128), with squares <= 2^32"),
    Constant("roots", "if big > wp.float64(1.0e-280):", "if big > wp.float64({value}):", _f32(2.0**-80), 1,
             "bracket_split jumps to big * 2^-32 only while that stays normal: float64 1e-280 (~2^-930, "
             "60 binades above 2^-1022 after the jump) -> 2^-80 (2^-112 after the jump, 14 above 2^-126)"),
    Constant("roots", "BALANCE_SPREAD = wp.constant(wp.float64(1.0261652496336e-289))",
             "BALANCE_SPREAD = wp.constant(wp.float64({value}))", _f32(2.0**-100), 1,
             "2^-960 underflows float32; coefficients within 2^-100 of the largest keep 26 binades "
             "(more than a mantissa) above float32's subnormal range after scaling to ~1 (float64: 62)"),
    Constant("roots", "wp.float64(1000.0)", "wp.float64({value})", _f32(120.0), 2,
             "scaled_root_limit keeps t_max/2^L within 2^+-1000: 2^1000 overflows float32 -> 2^+-120"),
    Constant("roots", "wp.float64(-1000.0)", "wp.float64({value})", _f32(-120.0), 2,
             "scaled_root_limit lower end (see above)"),
    Constant("roots", "SMALL_ARGUMENT = wp.constant(wp.float64(7.888609052210118e-31))",
             "SMALL_ARGUMENT = wp.constant(wp.float64({value}))", _f32(2.0**-16), 1,
             "brackets below 2^-100 are searched rescaled so cubic terms do not underflow; float32: "
             "x^3 at 2^-16 is 2^-48, 78 binades above 2^-126 (room for small coefficients)"),
    Constant("roots", "wp.float64(6.223015277861142e-61)", "wp.float64({value})", _f32(2.0**-32), 1,
             "quadratic discriminant scale k: squares of [2^-200, 2^200] fit float64, float32 needs "
             "[2^-32, 2^32] (squares within 2^+-64, far from 2^-126 / 2^128)"),
    Constant("roots", "wp.float64(1.6069380442589903e60)", "wp.float64({value})", _f32(2.0**32), 1,
             "upper end of the discriminant scale range (see above)"),
    Constant("roots", "wp.float64(-1.0e300)", "wp.float64({value})", _f32(-1.0e38), 1,
             "deflation score sentinel: -1e300 is -inf in float32 and must stay below the -1e299 one"),
    Constant("roots", "wp.float64(-1.0e299)", "wp.float64({value})", _f32(-1.0e37), 2,
             "score of a zero factor: must compare above the initial best score (both -inf otherwise)"),
    Constant("roots", "wp.float64(1.0e300)", "wp.float64({value})", _f32(1.0e30), 1,
             "cap of the clamp M * S in cubic_root_jacobian: a few-term sum of it must stay finite "
             "(float64: 1e300, 1.8e8 below DBL_MAX; float32: 1e30, 3.4e8 below FLT_MAX)"),
    Constant("ccd_common", "UNIT_ROUNDOFF = wp.constant(wp.float64(1.1102230246251565e-16))",
             "UNIT_ROUNDOFF = wp.constant(wp.float64({value}))", _f32(UNIT_ROUNDOFF["float32"]), 1,
             "unit roundoff of float32, 2^-24 (all CCD error bounds scale with it)"),
    Constant("ccd_common", "COPLANAR_RELATIVE = wp.constant(wp.float64(1.0e-12))",
             "COPLANAR_RELATIVE = wp.constant(wp.float64({value}))", _f32(2.0**-16), 1,
             "'coplanar for the whole step' threshold, 2^-16 = 256 u32 (4x the 64 u coefficient error): "
             "that branch finds contacts only at vertex-edge collinearity times, so it may only take "
             "motions whose out-of-plane part is within the distance tolerance (256 u). The float64 "
             "multiple (1e-12 ~ 9000 u64) gives 5.4e-4 in float32, which measured 3 false negatives on "
             "the sample queries (grazing contacts sent down that branch); 2^-16 measured none"),
    Constant("ccd_common", "CCD_T_MAX = wp.constant(wp.float64(1.0e150))",
             "CCD_T_MAX = wp.constant(wp.float64({value}))", _f32(T_MAX["float32"]), 1,
             "the solver's float32 t_max (see T_MAX)"),
    Constant("point_triangle", "wp.float64(1.0e-30)", "wp.float64({value})", _f32(2.88e-13), 1,
             "zero-area triangle test |n|^2 <= k max(|ab|^2, |ac|^2)^2, i.e. sin <= sqrt(k): "
             "1e-15 = 9 u64 -> 9 u32 = 5.37e-7, k = 2.88e-13 (below it the Voronoi regions are noise; "
             "the edge fallback then overestimates the distance by at most 5.4e-7 x the edge length, "
             "below the 256 u32 distance tolerance)"),
    Constant("ccd", "wp.float64(1.0e308) * wp.float64(10.0)", "wp.float64({value}) * wp.float64(10.0)", _f32(3.0e38), 1,
             "infinity as an overflowing product: 1e308 is not a float32 (3e38 * 10 overflows to inf)"),
)
"""The float32 values of the precision-dependent constants (see the module docstring)."""

KNOB_CONSTANTS = (
    Constant("roots", "NEWTON_MAX_ITERATIONS = wp.constant(256)", "NEWTON_MAX_ITERATIONS = wp.constant({value})",
             lambda s: int(s.max_iterations), 1, "max_iterations knob"),
    Constant("roots", "NEWTON_RELATIVE_TOLERANCE = wp.constant(wp.float64(4.440892098500626e-16))",
             "NEWTON_RELATIVE_TOLERANCE = wp.constant(wp.float64({value}))", lambda s: float(s.tolerance), 1,
             "tolerance knob (default 2 ulp of the precision)"),
    Constant("ccd_common", "COEFFICIENT_ERROR_FACTOR = wp.constant(wp.float64(64.0))",
             "COEFFICIENT_ERROR_FACTOR = wp.constant(wp.float64({value}))", lambda s: 64.0 * s.tolerance_scale, 1,
             "tolerance_scale knob on the coefficient error bound"),
    Constant("ccd_common", "DISTANCE_ERROR_FACTOR = wp.constant(wp.float64(256.0))",
             "DISTANCE_ERROR_FACTOR = wp.constant(wp.float64({value}))", lambda s: 256.0 * s.tolerance_scale, 1,
             "tolerance_scale knob on the distance error bound"),
)

_TYPE_RENAMES = {
    "wp.float64": "wp.float32",
    "wp.vec2d": "wp.vec2f",
    "wp.vec3d": "wp.vec3f",
    "wp.vec4d": "wp.vec4f",
    "wp.mat22d": "wp.mat22f",
    "wp.mat33d": "wp.mat33f",
    "wp.mat44d": "wp.mat44f",
}
_TYPE_RE = re.compile(r"\b(" + "|".join(re.escape(k) for k in _TYPE_RENAMES) + r")\b")
# float64-only Warp names that would survive the renames (a new type used in the kernels)
_LEFTOVER_RE = re.compile(r"\bwp\.(float64|(vec|mat|quat|transform|spatial_vector|spatial_matrix)\w*d)\b")
_IMPORT_RE = re.compile(r"^(\s*from\s+)kernels\.(\w+)(\s+import\b)", re.MULTILINE)

_WARP_IMPORT = "import warp as wp\n"
_FORWARD_ONLY = (
    "\n# generated variants are forward-only (kernels/variants.py): no adjoint code is compiled\n"
    "wp.set_module_options({\"enable_backward\": False})\n"
)

_lock = threading.Lock()
_cache: dict = {}  # (Settings, generate) -> KernelVariant


class KernelVariant:
    """The modules of one variant (attributes ``roots``, ``ccd_common``, ``point_triangle``,
    ``edge_edge``, ``ccd``), its :class:`Settings`, and ``package`` (None for the originals)."""

    def __init__(self, settings: Settings, modules: dict, package: str | None, directory: Path | None):
        self.settings = settings
        self.package = package
        self.directory = directory
        for name in MODULES:
            setattr(self, name, modules[name])

    def __repr__(self) -> str:
        return f"KernelVariant({self.settings}, package={self.package!r})"


def check_settings(precision="float64", max_iterations=None, tolerance=None, tolerance_scale=1.0) -> Settings:
    """Validated, normalised :class:`Settings`; ``None`` means the precision's default.

    Raises:
        ValueError: naming the argument: ``precision`` not in :data:`PRECISIONS`,
            ``max_iterations`` not a positive integer, ``tolerance`` / ``tolerance_scale`` not
            positive and finite.
    """
    if not isinstance(precision, str) or precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if max_iterations is None:
        max_iterations = DEFAULT_MAX_ITERATIONS
    else:
        try:
            if isinstance(max_iterations, bool):
                raise TypeError
            value = operator.index(max_iterations)
        except TypeError:
            raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}") from None
        if value < 1 or value > 2**31 - 1:
            raise ValueError(f"max_iterations must be a positive integer (< 2^31), got {max_iterations!r}")
        max_iterations = value
    if tolerance is None:
        tolerance = DEFAULT_TOLERANCE[precision]
    else:
        tolerance = _positive(tolerance, "tolerance")
        if precision == "float32" and not _FLT_MIN_NORMAL <= tolerance <= _FLT_MAX:
            raise ValueError(f"tolerance must be a normal float32 value for precision='float32', got {tolerance!r}")
    tolerance_scale = _positive(tolerance_scale, "tolerance_scale")
    if precision == "float32" and not _FLT_MIN_NORMAL <= 256.0 * tolerance_scale <= _FLT_MAX:
        raise ValueError(f"tolerance_scale out of float32 range, got {tolerance_scale!r}")
    return Settings(precision, max_iterations, tolerance, tolerance_scale)


def _positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def kernel_variant(precision="float64", *, max_iterations=None, tolerance=None, tolerance_scale=1.0,
                   generate: bool = False) -> KernelVariant:
    """The root-solver and narrow-phase modules for a precision and knob settings.

    Args:
        precision: ``"float64"`` (the kernels as written) or ``"float32"``.
        max_iterations: Newton-bisection iteration cap (default 256).
        tolerance: Newton relative step tolerance (default 2 ulp: 2^-51 / 2^-22).
        tolerance_scale: multiplier (> 0, default 1) of the CCD's coefficient and distance error
            bounds.
        generate: also generate a package for the default settings (a float64 copy of the
            kernels, to test the generator); otherwise the defaults return the original modules.

    Returns:
        :class:`KernelVariant` (cached per settings; the originals for the defaults).

    Raises:
        ValueError: a bad setting (the message names the argument); RuntimeError: the kernels'
        source no longer matches a substitution (update :data:`FLOAT32_CONSTANTS`).
    """
    # the types too: True == 1 as a dict key, but True is not a valid max_iterations
    key = (precision, max_iterations, tolerance, tolerance_scale, generate,
           type(max_iterations), type(tolerance), type(tolerance_scale))
    hit = _cache.get(key)
    if hit is not None:
        return hit
    settings = check_settings(precision, max_iterations, tolerance, tolerance_scale)
    with _lock:
        norm_key = (settings, bool(generate) and settings.is_default)
        variant = _cache.get(norm_key)
        if variant is None:
            if settings.is_default and not generate:
                modules = {name: importlib.import_module(f"kernels.{name}") for name in MODULES}
                variant = KernelVariant(settings, modules, None, None)
            else:
                variant = _build(settings)
            _cache[norm_key] = variant
        _cache[key] = variant
    return variant


def _sources() -> dict:
    return {name: (_KERNELS_DIR / f"{name}.py").read_text() for name in MODULES}


def generate_sources(settings: Settings, package: str) -> dict:
    """The variant's module sources (``{name: text}``) for ``settings``, importing from ``package``."""
    originals = _sources()
    rules = [c for c in KNOB_CONSTANTS]
    if settings.precision == "float32":
        rules += list(FLOAT32_CONSTANTS)
    out = {}
    for name, text in originals.items():
        mine = [c for c in rules if c.module == name]
        for c in mine:
            n = text.count(c.old)
            if n != c.count:
                raise RuntimeError(
                    f"kernels/variants.py: expected {c.count} occurrence(s) of {c.old!r} in kernels/{name}.py, "
                    f"found {n}; the kernels changed: update the substitution table")
        if mine:
            table = {c.old: c.new.replace("{value}", repr(c.value(settings))) for c in mine}
            pattern = re.compile("|".join(re.escape(k) for k in sorted(table, key=len, reverse=True)))
            text = pattern.sub(lambda m, t=table: t[m.group(0)], text)  # one pass: no cascading
        if settings.precision == "float32":
            text = _TYPE_RE.sub(lambda m: _TYPE_RENAMES[m.group(1)], text)
            left = _LEFTOVER_RE.search(_code_only(text))
            if left:
                raise RuntimeError(f"kernels/variants.py: kernels/{name}.py uses {left.group(0)}, which has no float32 rename")
            _check_float32_literals(name, text)
        text = _IMPORT_RE.sub(lambda m: f"{m.group(1)}{package}.{m.group(2)}{m.group(3)}", text)
        for mod in re.findall(rf"from\s+{re.escape(package)}\.(\w+)\s+import", text):
            if mod not in MODULES:
                raise RuntimeError(f"kernels/{name}.py imports kernels.{mod}, which is not part of a variant")
        if re.search(r"^\s*(import|from)\s+kernels\b", text, re.MULTILINE):
            raise RuntimeError(f"kernels/{name}.py imports the kernels package in a form the generator cannot rewrite")
        if text.count(_WARP_IMPORT) != 1:
            raise RuntimeError(f"kernels/{name}.py must import warp exactly once as {_WARP_IMPORT.strip()!r}")
        text = text.replace(_WARP_IMPORT, _WARP_IMPORT + _FORWARD_ONLY)
        header = (f"# GENERATED by kernels/variants.py from kernels/{name}.py -- do not edit.\n"
                  f"# settings: {settings}\n")
        out[name] = header + text
    return out


def _code_only(text: str) -> str:
    """The source without comments and string literals (docstrings)."""
    parts = []
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.STRING):
            parts.append(tok.string)
    return " ".join(parts)


def _check_float32_literals(name: str, text: str) -> None:
    """Every float literal in the code must be a normal float32 (or zero)."""
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type != tokenize.NUMBER or not re.search(r"[.eE]", tok.string) or tok.string.lower().startswith("0x"):
            continue
        v = abs(float(tok.string))
        if v != 0.0 and not (_FLT_MIN_NORMAL <= v <= _FLT_MAX):
            raise RuntimeError(
                f"kernels/variants.py: float32 variant of kernels/{name}.py keeps the literal {tok.string} "
                f"(line {tok.start[0]}), outside float32's normal range: add it to FLOAT32_CONSTANTS")


def _variant_root() -> Path:
    import warp as wp

    if wp.config.kernel_cache_dir is None:
        wp.init()
    base = wp.config.kernel_cache_dir or os.path.join(tempfile.gettempdir(), f"tunnelsim_warp_{os.getuid()}")
    return Path(base) / "tunnelsim_variants"


def _write_atomic(path: Path, text: str) -> None:
    try:
        if path.read_text() == text:
            return
    except OSError:
        pass
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _build(settings: Settings) -> KernelVariant:
    originals = _sources()
    digest = hashlib.sha256()
    digest.update(GENERATOR_VERSION.encode())
    digest.update(repr(settings).encode())
    for name in MODULES:
        digest.update(name.encode() + b"\0" + originals[name].encode() + b"\0")
    package = f"tunnelsim_kv_{settings.precision}_{digest.hexdigest()[:16]}"
    sources = generate_sources(settings, package)
    directory = _variant_root() / package
    directory.mkdir(parents=True, exist_ok=True)
    for name, text in sources.items():
        _write_atomic(directory / f"{name}.py", text)
    _write_atomic(directory / "__init__.py", f'"""Generated kernel variant ({settings}); see kernels/variants.py."""\n')
    importlib.invalidate_caches()
    if package not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            package, directory / "__init__.py", submodule_search_locations=[str(directory)])
        pkg = importlib.util.module_from_spec(spec)
        sys.modules[package] = pkg
        try:
            spec.loader.exec_module(pkg)
        except BaseException:
            sys.modules.pop(package, None)
            raise
    modules = {name: importlib.import_module(f"{package}.{name}") for name in MODULES}
    return KernelVariant(settings, modules, package, directory)


def _check_defaults() -> None:
    """The defaults above must be the kernels' own values (cheap text check, at import)."""
    text = (_KERNELS_DIR / "roots.py").read_text()
    if f"NEWTON_MAX_ITERATIONS = wp.constant({DEFAULT_MAX_ITERATIONS})" not in text:
        raise RuntimeError("kernels/variants.py: DEFAULT_MAX_ITERATIONS differs from kernels/roots.py")
    if f"NEWTON_RELATIVE_TOLERANCE = wp.constant(wp.float64({DEFAULT_TOLERANCE['float64']!r}))" not in text:
        raise RuntimeError("kernels/variants.py: DEFAULT_TOLERANCE differs from kernels/roots.py")


_check_defaults()
