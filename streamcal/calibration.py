"""The calibration result: a versioned value with units that applies itself to (N,3) arrays.

Model (docs/calibration_file.md): ``m = K x + b + Σ effect terms + noise``, ``x`` the unit field
direction in the sensor (body) frame, ``K`` upper triangular with a positive diagonal (the
canonical form), ``b`` the offset, both in the sensor's unit (µT for ``sensor: mag``, m/s² for
``sensor: accel`` unless the track declares another unit).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Any, Mapping

import numpy as np

from .atomic import atomic_write_text
from .errors import CalibrationFileError
from .model import invert_model, validate_effect_params
from .model.catalog import EFFECT_NAMES

FORMAT = "streamcal-calibration/1"
SENSORS = ("mag", "accel")
DEFAULT_MODEL = ("hard_iron", "soft_iron")
#: Largest calibration file we agree to parse (bytes); real ones are < 10 kB.
MAX_FILE_BYTES = 1 << 20


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def field_radius(K: np.ndarray) -> float:
    """Geometric-mean radius of the sensor matrix ``K`` (3,3), sensor unit: |det K|^(1/3)
    (for the canonical upper-triangular K the geometric mean of its diagonal)."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(K, dtype=float).tolist()
    # the 3×3 determinant by cofactors (np.linalg.det's call costs ~5× its arithmetic here)
    return float(np.cbrt(abs(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))))


def _frozen(value, shape) -> np.ndarray:
    """A read-only float copy of ``value`` reshaped to ``shape`` (the caller's array is left
    writeable)."""
    arr = np.array(value, dtype=float).reshape(shape)
    arr.flags.writeable = False
    return arr


def canonical_form(A: np.ndarray, directions: np.ndarray | None = None):
    """Write a general 3×3 sensor matrix ``A`` as ``K Q`` (RQ decomposition), ``K`` upper
    triangular with positive diagonal, ``Q`` orthogonal; return ``(K, Q)``.

    ``A x = K (Q x)``, so directions expressed for ``K`` are ``Q x``; pass ``directions`` (N,3)
    to get them rotated as a third return value.
    """
    import scipy.linalg

    A = np.asarray(A, dtype=float)
    K, Q = scipy.linalg.rq(A)
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    K = K * signs[None, :]
    Q = signs[:, None] * Q
    K = np.triu(K)
    if directions is None:
        return K, Q
    return K, Q, np.asarray(directions) @ Q.T


@dataclass(frozen=True, eq=False)
class Calibration:
    """A fitted sensor model: a value. ``K`` and ``b`` are read-only arrays; two calibrations
    are equal (and hash equal) when their saved content (:meth:`to_dict`) is, but for the
    ``created`` stamp: the same fit made twice is the same calibration. The per-sample results
    (``inliers``, ``weights``, ``directions``) travel with it but are neither saved nor compared.

    Attributes:
        K: (3,3) upper triangular, positive diagonal, sensor unit per unit direction.
        b: (3,) offset in the sensor unit.
        sensor: ``"mag"`` or ``"accel"``.
        model: effect names of docs/effects.md that the model contains.
        effects: parameters of the effects beyond K and b, ``{name: {param: value}}``.
        rms: sensor estimation error over inliers (paper eq. 41), sensor unit.
        n, n_outliers: samples used and samples classified as outliers.
        coverage: fraction of the sphere of directions covered (0..1), if known.
        unit: the sensor unit (``"uT"``, ``"m/s^2"``, ``"counts"``…).
        field: local field strength (``field_uT`` in the file) when known.
        inliers, weights, directions: per-sample results of the fit (not stored in the file):
            bool (N,), robust weights (N,) in [0, 1], unit directions (N,3).
    """

    K: np.ndarray
    b: np.ndarray
    sensor: str = "mag"
    model: tuple[str, ...] = DEFAULT_MODEL
    effects: Mapping[str, Mapping[str, Any]] = _field(default_factory=dict)
    rms: float = float("nan")
    n: int = 0
    n_outliers: int = 0
    coverage: float | None = None
    unit: str = "uT"
    field: float | None = None
    method: str = "autocal"
    kernel: str | None = None
    created: str = _field(default_factory=_utc_now, compare=False)
    inliers: np.ndarray | None = _field(default=None, compare=False, repr=False)
    weights: np.ndarray | None = _field(default=None, compare=False, repr=False)
    directions: np.ndarray | None = _field(default=None, compare=False, repr=False)
    extra: Mapping[str, Any] = _field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "K", _frozen(self.K, (3, 3)))
        object.__setattr__(self, "b", _frozen(self.b, (3,)))
        object.__setattr__(self, "model", tuple(self.model))

    def __eq__(self, other) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return self._content() == other._content()

    def __hash__(self) -> int:
        return hash(json.dumps(self._content(), allow_nan=False))

    def _content(self) -> dict:
        """What equality compares: :meth:`to_dict` without ``created``."""
        out = self.to_dict()
        out.pop("created")
        return out

    def _repr_html_(self) -> str:
        """Jupyter's view: model, K and b, each effect's parameters, rms, n and outliers, all
        with units; every text escaped."""
        from .units import effect_params, quantity
        from .values import html_table

        u = self.unit
        rows = [("model", ", ".join(self.model)), ("sensor", self.sensor),
                *((f"K row {i + 1}", quantity(row, u, 5)) for i, row in enumerate(self.K)),
                ("b", quantity(self.b, u, 5)),
                *((name, effect_params(name, params, u)) for name, params in self.effects.items()),
                ("rms", f"{quantity(self.rms, u, 4)} ({self.residual} residual)"
                 if math.isfinite(self.rms) else "unknown"),
                ("n", f"{self.n} samples, {self.n_outliers} outliers"),
                ("coverage", "unknown" if self.coverage is None else f"{self.coverage:.0%}"),
                ("method", self.method + (f", {self.kernel} kernel" if self.kernel else ""))]
        return html_table(rows, caption="Calibration")

    @property
    def residual(self) -> str:
        """The residual ``rms`` is on: ``"sensor"`` (eq. 41, every direction free), or
        ``"gravity_tied"`` / ``"gyro_tied"`` for a fit with a registration effect."""
        return rms_residual(self)

    def __str__(self) -> str:
        """A few lines for a reader: sensor and model, K's diagonal and b with units, the rms
        with its residual, samples, outliers and coverage (the file has everything:
        :meth:`to_json`)."""
        from .units import effect_params, quantity

        from .units import display_unit

        u = self.unit
        lines = [f"Calibration of {self.sensor} ({self.method}"
                 + (f", {self.kernel} kernel" if self.kernel else "") + f"): {', '.join(self.model)}"
                 + ("" if display_unit(u) else "; unit unknown"),
                 f"  K diagonal {quantity(np.diag(self.K), u, 4)} per unit direction"
                 + ("" if not np.any(np.triu(self.K, 1)) else
                    f" (off-diagonal up to {quantity(np.abs(np.triu(self.K, 1)).max(), u)})"),
                 f"  b          {quantity(self.b, u, 4)}"]
        for name, params in self.effects.items():
            lines.append(f"  {name}: {effect_params(name, params, u)}")
        rms = (f"{quantity(self.rms, u, 4)} on the {self.residual.replace('_', '-')} residual"
               if math.isfinite(self.rms) else "unknown")
        lines.append(f"  rms        {rms} over {self.n - self.n_outliers} inliers "
                     f"({self.n_outliers} outliers of {self.n} samples)")
        extra = []
        if self.coverage is not None:
            extra.append(f"coverage {self.coverage:.0%} of the sphere")
        if self.field:
            extra.append(f"field {quantity(self.field, u, 4)}")
        else:
            extra.append(f"radius {quantity(self.radius, u, 4)}")
        lines.append("  " + ", ".join(extra))
        return "\n".join(lines)

    def __repr__(self) -> str:
        from .units import quantity

        return (f"<Calibration {self.sensor} {'+'.join(self.model)}: rms "
                f"{quantity(self.rms, self.unit, 4)} "
                f"({self.residual}), n={self.n}, {self.n_outliers} outliers>")

    @property
    def radius(self) -> float:
        """Geometric-mean radius of ``K`` (:func:`field_radius`), sensor unit."""
        return field_radius(self.K)

    # -- using it ---------------------------------------------------------------------------
    def apply(self, m, covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Calibrated unit directions ``x = K⁻¹ (m − b − effect terms)``, shape (N,3).

        ``m`` is (N,3) or (3,) in the sensor unit; ``covariates`` maps track column names
        (``t``, ``temp``, aux channels…) to (N,) arrays, needed when the model has effects
        beyond K and b. The result is *not* renormalised, so its norm shows the remaining error.
        """
        m = np.asarray(m, dtype=float)
        single = m.ndim == 1
        m2 = np.atleast_2d(m)
        if self.effects:
            x = invert_model(self, m2, covariates or {})
        else:
            x = np.linalg.solve(self.K, (m2 - self.b).T).T
        return x[0] if single else x

    def apply_field(self, m, covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Calibrated field vectors ``|B| x`` (N,3) in the sensor unit; ``|B|`` is ``field`` when
        known, else :attr:`radius` (K's geometric-mean radius)."""
        return (self.field or self.radius) * self.apply(m, covariates)

    def model_error(self, other: "Calibration") -> float:
        """Normalized model deviation ‖[K,b] − [K',b']‖_F / ‖[K',b']‖_F (paper eq. 39/40)."""
        a = np.hstack([self.K, self.b[:, None]])
        ref = np.hstack([other.K, other.b[:, None]])
        return float(np.linalg.norm(a - ref) / np.linalg.norm(ref))

    def replace(self, **changes) -> "Calibration":
        return dataclasses.replace(self, **changes)

    # -- JSON -------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The calibration file's keys (docs/calibration_file.md)."""
        out = {
            "format": FORMAT,
            "sensor": self.sensor,
            "model": list(self.model),
            "K": [[float(v) for v in row] for row in self.K],
            "b": [float(v) for v in self.b],
            "effects": jsonable(self.effects),
            "rms": _finite_or_none(self.rms),
            "residual": self.residual,
            "n": int(self.n),
            "n_outliers": int(self.n_outliers),
            "coverage": _finite_or_none(self.coverage),
            "unit": self.unit,
            "method": self.method,
            "created": self.created,
        }
        if self.kernel is not None:
            out["kernel"] = self.kernel
        if self.field is not None:
            out["field_uT" if self.unit == "uT" else "field"] = float(self.field)
        for key, value in self.extra.items():
            out.setdefault(key, jsonable(value))
        return out

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def save(self, path: str | os.PathLike) -> None:
        """Write the calibration file atomically (temp file, fsync, rename)."""
        atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<calibration>") -> "Calibration":
        """The calibration :meth:`to_dict` (a calibration file's parsed JSON) describes,
        validated as :meth:`load` does (``CalibrationFileError`` naming ``source`` and the key);
        ``Calibration.from_dict(cal.to_dict()) == cal``."""
        return _parse(data, source)

    @classmethod
    def from_json(cls, text: str, source: str = "<calibration>") -> "Calibration":
        try:
            data = json.loads(text, parse_constant=_reject_constant)
        except (json.JSONDecodeError, ValueError, RecursionError) as exc:
            raise CalibrationFileError(f"{source}: not valid JSON ({exc})") from None
        return _parse(data, source)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Calibration":
        """Read and validate a calibration file. A symbolic link is refused (opened with
        ``O_NOFOLLOW``: a link planted where a calibration is expected cannot redirect the
        read); files over :data:`MAX_FILE_BYTES` are refused."""
        path = os.fspath(path)
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError as exc:
            reason = "is a symbolic link; refusing to follow it" if os.path.islink(path) \
                else f"cannot read ({exc.strerror or exc})"
            raise CalibrationFileError(f"{path}: {reason}") from None
        try:
            with os.fdopen(fd, "rb") as handle:
                raw = handle.read(MAX_FILE_BYTES + 1)
        except OSError as exc:   # e.g. a directory
            raise CalibrationFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
        if len(raw) > MAX_FILE_BYTES:
            raise CalibrationFileError(f"{path}: {len(raw)} bytes or more is too large for a "
                                       "calibration file (a small JSON file; a recording or a "
                                       "log goes where the command reads one)")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CalibrationFileError(f"{path}: not a calibration file: a calibration is JSON "
                                       f"text, and byte {exc.start} is not UTF-8 (a binary "
                                       "file, such as a flight log?)") from None
        return cls.from_json(text, source=path)


#: The residual families an rms can be on.
RESIDUALS = ("sensor", "gravity_tied", "gyro_tied")


def rms_residual(cal) -> str:
    """``"sensor"``, ``"gravity_tied"`` or ``"gyro_tied"``: the residual ``cal.rms`` is on."""
    from .model import REGISTRATION_EFFECTS

    extra = getattr(cal, "extra", None) or {}
    if "gyro_tied" in extra:
        return "gyro_tied"
    if any(n in REGISTRATION_EFFECTS for n in cal.model) and "gravity" in extra:
        return "gravity_tied"
    return "sensor"


def _reject_constant(name):
    raise ValueError(f"non-finite number {name} is not allowed")


def _finite_or_none(value):
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def jsonable(value):
    """``value`` in plain JSON types: a mapping → dict with str keys, a list, tuple or array →
    list, a numpy number or bool → the Python one, recursively; anything else as it is. A
    non-finite float (NaN, ±inf: an unobservable σ, an unknown rms) → None (JSON null): every
    JSON streamcal writes is strict (``allow_nan=False``), so that any parser reads it."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):   # nested lists of Python scalars (0-d: the scalar)
        return jsonable(np.asarray(value, dtype=object).tolist())
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return _finite_or_none(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


#: Keys every calibration file has (docs/calibration_file.md).
REQUIRED_KEYS = ("format", "sensor", "model", "K", "b", "n")


def _parse(data, source: str) -> Calibration:
    def fail(key, what):
        raise CalibrationFileError(f"{source}: key '{key}': {what}")

    if not isinstance(data, Mapping):
        raise CalibrationFileError(f"{source}: expected a JSON object, found {type(data).__name__}")
    if "format" in data and data["format"] != FORMAT:
        fail("format", f"expected '{FORMAT}', found {data.get('format')!r} (not a streamcal calibration?)")
    for key in REQUIRED_KEYS:
        if key not in data:
            raise CalibrationFileError(f"{source}: missing key '{key}'" + (
                " (not a streamcal calibration?)" if key == "format" else ""))
    sensor = data.get("sensor")
    if sensor not in SENSORS:
        fail("sensor", f"expected one of {SENSORS}, found {sensor!r}")
    model = data.get("model")
    if not isinstance(model, list) or not all(isinstance(m, str) for m in model):
        fail("model", "expected a list of effect names")

    for name in model:
        if name not in EFFECT_NAMES:
            fail("model", f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    K = _matrix(data.get("K"), (3, 3), "K", fail)
    if np.any(np.tril(K, -1) != 0):
        fail("K", "must be upper triangular (canonical form)")
    if np.any(np.diag(K) <= 0):
        fail("K", "diagonal must be positive")
    b = _matrix(data.get("b"), (3,), "b", fail)
    effects = data.get("effects", {})
    if not isinstance(effects, Mapping):
        fail("effects", "expected an object {effect: {parameter: value}}")
    for name, params in effects.items():
        if name not in EFFECT_NAMES:
            fail("effects", f"unknown effect {name!r}")
        if not isinstance(params, Mapping):
            fail(f"effects.{name}", "expected an object of parameters")
    if effects:

        try:
            validate_effect_params(effects)
        except ValueError as exc:
            fail("effects", str(exc))
    numbers = {}
    for key, kind, required in (("rms", float, False), ("n", int, True), ("n_outliers", int, False),
                                ("coverage", float, False)):
        value = data.get(key)
        if value is None:
            if required:
                fail(key, "missing")
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(key, f"expected a finite number, found {value!r}")
        if kind is int and (value != int(value) or value < 0):
            fail(key, f"expected a non-negative integer, found {value!r}")
        numbers[key] = kind(value)
    if "coverage" in numbers and not 0 <= numbers["coverage"] <= 1:
        fail("coverage", f"expected a fraction in [0, 1], found {numbers['coverage']}")
    unit = data.get("unit", "uT" if sensor == "mag" else "m/s^2")
    field_value = data.get("field_uT", data.get("field"))
    if field_value is not None and (isinstance(field_value, bool) or not isinstance(field_value, (int, float))
                                    or not math.isfinite(field_value) or field_value <= 0):
        fail("field_uT", f"expected a positive number, found {field_value!r}")
    for key in ("unit", "method", "kernel"):
        if data.get(key) is not None and not isinstance(data[key], str):
            fail(key, f"expected a string, found {type(data[key]).__name__}")
    created = data.get("created", "")
    if not isinstance(created, str):
        fail("created", "expected an ISO-8601 string")
    if data.get("residual") is not None and data["residual"] not in RESIDUALS:
        fail("residual", f"expected one of {', '.join(RESIDUALS)}, found {data['residual']!r}")
    # "residual" is derived from the model and the extra keys (rms_residual), never stored
    known = {"format", "sensor", "model", "K", "b", "effects", "rms", "residual", "n", "n_outliers",
             "coverage", "unit", "field_uT", "field", "method", "kernel", "created"}
    extra = {k: v for k, v in data.items() if k not in known}
    return Calibration(K=K, b=b, sensor=sensor, model=tuple(model), effects=dict(effects),
                       rms=numbers.get("rms", float("nan")), n=numbers["n"],
                       n_outliers=numbers.get("n_outliers", 0), coverage=numbers.get("coverage"),
                       unit=str(unit), field=None if field_value is None else float(field_value),
                       method=str(data.get("method", "autocal")), kernel=data.get("kernel"),
                       created=created, extra=extra)


def _numbers(value, depth: int) -> bool:
    """True if ``value`` is a list nested ``depth`` deep of JSON numbers (no strings, no bools)."""
    if depth == 0:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, list) and all(_numbers(v, depth - 1) for v in value)


def _matrix(value, shape, key, fail) -> np.ndarray:
    if not _numbers(value, len(shape)):
        fail(key, f"expected numbers of shape {shape}")
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        fail(key, f"expected numbers of shape {shape}")
    if arr.shape != shape:
        fail(key, f"expected shape {shape}, found {arr.shape}")
    if not np.all(np.isfinite(arr)):
        fail(key, "contains a non-finite value")
    return arr
