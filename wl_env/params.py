"""Loader parameters: the defaults of the model specification, with their provenance.

The numbers are copied from the project's model specification (``shared/spec/params.json``, Volvo L220G
class machine) so that the simulator, the optimal control problem and the MPC all use one parameter set.
``source`` notes: *paper* = Nezhadali & Eriksson (the reference paper), *reimpl* = public
re-implementations of the same Linkoping model family, *derived* = computed from other entries,
*assumed* = chosen by the specification with the reason given.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from dataclasses import dataclass, field
from typing import Any

# field name -> (unit, provenance).  Kept beside the dataclass so `describe()` and the docs can print it.
PROVENANCE: dict[str, tuple[str, str]] = {
    "g": ("m/s^2", "physics"),
    "J_ice": ("kg m^2", "reimpl"),
    "eta_ig": ("-", "reimpl (LiU 12.7 L engine: 0.6877*(1-17.3^-0.35))"),
    "q_hv": ("J/kg", "reimpl"),
    "n_cyl": ("-", "reimpl"),
    "V_d": ("m^3", "reimpl"),
    "c_fr": ("bar, with N in krpm: FMEP = c1*N^2 + c2*N + c3", "reimpl (LiU 12.7 L engine)"),
    "U_mf_max": ("mg/cycle/cyl", "reimpl"),
    "T_max_lines": (
        "[a, b]: T_ice <= a + b*N, N in rpm",
        "digitized from the model family's engine map (Fig. 7 of the paper); peak power ~278 kW at "
        "~1380 rpm, L220G brochure 274 kW",
    ),
    "omega_min": ("rad/s", "reimpl (~544 rpm)"),
    "omega_max": ("rad/s", "reimpl (~2200 rpm)"),
    "omega_0": ("rad/s", "paper Table II: 1500 rpm exactly (params.json's 157.08 rad/s is that, rounded)"),
    "tc_xi_poly": ("N m/krpm^2, highest power first, 0<=phi<=1.5", "reimpl (fit of the paper's Fig. 5)"),
    "tc_kappa_poly": ("N m/krpm^2, highest power first, 0<=phi<=1.5", "reimpl (fit of the paper's Fig. 5)"),
    "tc_phi_hi": ("-", "assumed: above this (and below 0) the polynomials continue linearly, C1"),
    "eta_gb": ("-", "reimpl"),
    "gear_ratio": ("-", "paper (gamma = -60 / 0 / +60)"),
    "r_w": ("m", "paper (1.5 wheel circumferences = 6.6 m)"),
    "J_w": ("kg m^2 per wheel", "reimpl"),
    "M_veh": ("kg", "reimpl (L220G operating weight ~32 t)"),
    "M_load": ("kg", "reimpl (bucket + rated payload)"),
    "c_r": ("-", "reimpl"),
    "eta_lift": ("-", "reimpl"),
    "M_boom": ("kg", "reimpl"),
    "I_boom": ("kg m^2", "assumed: M_boom*r^2/3 (slender beam about its end)"),
    "G": ("m", "reimpl (boom pivot height)"),
    "r1": ("m", "reimpl"),
    "r2": ("m", "reimpl"),
    "x_c": ("m", "assumed: lift cylinder frame joint; k(theta2) in 2.6..3.3, stroke ~1.4 m"),
    "y_c": ("m", "assumed: see x_c"),
    "n_lift_cyl": ("-", "reimpl / L220G"),
    "r_piston": ("m", "reimpl (190 mm bore)"),
    "r_rod": ("m", "reimpl (90 mm rod)"),
    "P_cyl_max": ("Pa", "assumed: typical working-hydraulics relief pressure"),
    "D_pump": ("m^3/rev", "assumed effective displacement: full-flow lift 0.7->5 m takes ~5-6 s"),
    "pump_speed_sat": ("rad/s", "paper (pump speed saturates at ~1500 rpm)"),
    "eta_vol": ("-", "reimpl"),
    "eta_cyl": ("-", "assumed: typical cylinder efficiency"),
    "U_ab_bounds": ("m/s^2", "assumed (optimal traces of the model family span -2.4..1.6)"),
    "U_b_max": ("N m, total at the wheels", "digitized: active bound in the minimum-time brake trace"),
    "V_max": ("m/s", "derived: omega_max*r_w/gamma"),
    "decel_max": ("g", "paper eq. (31)"),
    "H_0": ("m", "paper Table II"),
    "H_T": ("m", "paper Table II"),
    "reverse_distance": ("m", "paper (6.6 m each way): from the pile to the reversing point"),
    "forward_distance": ("m", "paper (6.6 m each way): from the reversing point to the truck"),
}


@dataclass(frozen=True)
class Range:
    """An allowed interval, printed as in the error messages: [lo, hi], (lo, hi]..."""

    lo: float
    hi: float
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, v: float) -> bool:
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below

    def __str__(self) -> str:
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


_EFFICIENCY = Range(0.0, 1.0, lo_open=True)
# Allowed values of the scalar fields: physical limits with wide margins around the specification's
# machine (a 32 t loader), so that they reject nonsense (a negative mass, a 1e300 kg loader, an efficiency
# of 1.2) but not other machines, nor the robustness variants (payload x0.6..x3, rolling 0.015..0.05).
_REAL_RANGES: dict[str, Range] = {
    "g": Range(1.0, 30.0),
    "J_ice": Range(0.5, 100.0),
    "eta_ig": _EFFICIENCY,
    "q_hv": Range(1e7, 1.5e8),
    "V_d": Range(1e-3, 0.1),
    "U_mf_max": Range(10.0, 2000.0),
    "omega_min": Range(10.0, 200.0),
    "omega_max": Range(50.0, 500.0),
    "omega_0": Range(10.0, 500.0),
    "tc_phi_hi": Range(0.5, 3.0),
    "eta_gb": _EFFICIENCY,
    "gear_ratio": Range(1.0, 500.0),
    "r_w": Range(0.1, 3.0),
    "J_w": Range(1.0, 1e5),
    "M_veh": Range(1000.0, 3e5),
    "M_load": Range(0.0, 2e5),
    "c_r": Range(0.0, 0.5),
    "eta_lift": _EFFICIENCY,
    "M_boom": Range(10.0, 1e5),
    "I_boom": Range(1.0, 1e6),
    "G": Range(0.0, 10.0),
    "r1": Range(0.1, 10.0),
    "r2": Range(0.1, 10.0),
    "x_c": Range(-10.0, 10.0),
    "y_c": Range(-10.0, 10.0),
    "r_piston": Range(0.01, 1.0),
    "r_rod": Range(0.005, 1.0),
    "P_cyl_max": Range(1e6, 1e8),
    "D_pump": Range(1e-6, 1e-2),
    "pump_speed_sat": Range(1.0, 1000.0),
    "eta_vol": _EFFICIENCY,
    "eta_cyl": _EFFICIENCY,
    "U_b_max": Range(100.0, 1e7),
    "V_max": Range(0.1, 20.0),
    "decel_max": Range(0.01, 2.0),
    "H_0": Range(0.0, 20.0),
    "H_T": Range(0.0, 20.0, lo_open=True),
    "reverse_distance": Range(0.5, 100.0),
    "forward_distance": Range(0.5, 100.0),
}
_INT_RANGES: dict[str, Range] = {"n_cyl": Range(1, 24), "n_lift_cyl": Range(1, 8)}
# Vector fields: (length, range of each entry). The shapes are what the model's equations index.
_VECTORS: dict[str, tuple[int, Range]] = {
    "c_fr": (3, Range(-10.0, 10.0)),  # bar/krpm^2, bar/krpm, bar
    "tc_xi_poly": (7, Range(-1e5, 1e5)),
    "tc_kappa_poly": (7, Range(-1e5, 1e5)),
    "U_ab_bounds": (2, Range(-50.0, 50.0)),
}
_T_MAX_A, _T_MAX_B = Range(-1e5, 1e5), Range(-100.0, 100.0)  # N m, N m/rpm


@dataclass(frozen=True)
class LoaderParams:
    """Parameters of the wheel loader model (SI units unless the field's unit says otherwise).

    Defaults are the specification's (see ``PROVENANCE``). Instances are immutable and validated on
    construction; make variants with :meth:`replace` or :meth:`variant`.
    """

    g: float = 9.81
    J_ice: float = 3.0
    eta_ig: float = 0.434
    q_hv: float = 42.9e6
    n_cyl: int = 6
    V_d: float = 0.0127
    c_fr: tuple[float, float, float] = (0.7196, -0.1414, 0.3590)
    U_mf_max: float = 260.0
    T_max_lines: tuple[tuple[float, float], ...] = ((8.0, 2.086), (2200.0, 0.0), (3855.0, -1.40))
    omega_min: float = 57.0
    omega_max: float = 230.4
    omega_0: float = 1500.0 * (math.pi / 30.0)  # (as wl_env.scenario converts rpm)
    tc_xi_poly: tuple[float, ...] = (-57.24, -177.0, 1339.0, -1794.0, 334.3, -39.47, 406.2)
    tc_kappa_poly: tuple[float, ...] = (26.26, -176.9, 427.4, -341.0, -9.083, -598.1, 675.4)
    tc_phi_hi: float = 1.5
    eta_gb: float = 0.9
    gear_ratio: float = 60.0
    r_w: float = 0.70
    J_w: float = 1000.0
    M_veh: float = 32000.0
    M_load: float = 10000.0
    c_r: float = 0.03
    eta_lift: float = 0.9
    M_boom: float = 5000.0
    I_boom: float = 14000.0
    G: float = 2.3
    r1: float = 1.7
    r2: float = 1.2
    x_c: float = 0.30
    y_c: float = -0.90
    n_lift_cyl: int = 2
    r_piston: float = 0.095
    r_rod: float = 0.045
    P_cyl_max: float = 25.0e6
    D_pump: float = 5.0e-4
    pump_speed_sat: float = 157.08
    eta_vol: float = 0.98
    eta_cyl: float = 0.95
    U_ab_bounds: tuple[float, float] = (-2.5, 2.5)
    U_b_max: float = 57800.0
    V_max: float = 2.7
    decel_max: float = 0.18
    H_0: float = 0.7
    H_T: float = 5.0
    reverse_distance: float = 6.6
    forward_distance: float = 6.6

    # ---- derived constants (cached so hot paths do not recompute them) ----
    _derived: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Type, shape, finiteness and range of each field first, stored as float/int/tuple: the instance
        # stays hashable, and its fingerprint does not depend on how a number was spelled (32000 or 32000.0).
        for f in dataclasses.fields(self):
            if f.init:
                object.__setattr__(self, f.name, _coerce(f.name, getattr(self, f.name)))
        self._validate()
        d = self._derived
        d["r"] = self.r1 + self.r2
        d["A_piston"] = self.n_lift_cyl * math.pi * (self.r_piston**2 - self.r_rod**2)
        d["M_tot"] = self.M_veh + self.M_load + 4.0 * self.J_w / self.r_w**2
        d["F_roll"] = self.c_r * (self.M_veh + self.M_load) * self.g
        d["T_ig_per_mg"] = self.eta_ig * self.q_hv * self.n_cyl * 1e-6 / (4.0 * math.pi)
        d["T_fric_scale"] = self.V_d * 1e5 / (4.0 * math.pi)
        d["fuel_per_mg_rad"] = 1e-6 * self.n_cyl / (4.0 * math.pi)

    # Read-only accessors for derived constants.
    @property
    def r(self) -> float:
        """Boom length r = r1 + r2 (m)."""
        return self._derived["r"]

    @property
    def A_piston(self) -> float:
        """Total lift-cylinder area of eq. (17) as written, n_lift_cyl * pi * (r_piston^2 - r_rod^2) (m^2)."""
        return self._derived["A_piston"]

    @property
    def M_tot(self) -> float:
        """Translational plus wheel-equivalent mass, eq. (27) (kg)."""
        return self._derived["M_tot"]

    @property
    def F_roll(self) -> float:
        """Rolling resistance force, eq. (25) (N)."""
        return self._derived["F_roll"]

    @property
    def T_ig_per_mg(self) -> float:
        """Indicated torque per mg of injected fuel, eq. (6) (N m per mg/cycle)."""
        return self._derived["T_ig_per_mg"]

    @property
    def final_position(self) -> float:
        """Position s (m) of the truck, the end of the cycle: forward_distance - reverse_distance."""
        return self.forward_distance - self.reverse_distance

    @property
    def H_max(self) -> float:
        """Highest reachable bucket height G + r (m): the boom vertical."""
        return self.G + self.r

    def _validate(self) -> None:
        """The checks between fields (each field's own type and range are checked by :func:`_coerce`)."""
        if not self.omega_min < self.omega_max:
            raise ValueError(f"LoaderParams.omega_min must be below omega_max, got {self.omega_min} >= {self.omega_max} rad/s")
        if not self.omega_min < self.omega_0 < self.omega_max:
            raise ValueError(
                f"LoaderParams.omega_0 must lie in (omega_min, omega_max) = ({self.omega_min}, {self.omega_max}), "
                f"got {self.omega_0}"
            )
        lo, hi = self.U_ab_bounds
        if not lo < 0.0 < hi:
            raise ValueError(f"LoaderParams.U_ab_bounds must be (lo, hi) with lo < 0 < hi, got {self.U_ab_bounds}")
        if self.r_rod >= self.r_piston:
            raise ValueError(f"LoaderParams.r_rod must be < r_piston ({self.r_piston}), got {self.r_rod}")
        reach = 0.98 * (self.r1 + self.r2)  # the boom's end stops, wl_env.physics.lift.BOOM_SIN_MAX
        if not self.G - reach < self.H_0 < self.H_T < self.G + reach:
            raise ValueError(
                f"LoaderParams.H_T must satisfy H_0 < H_T < {self.G + reach:.3f} m (G + 0.98 (r1 + r2), the boom's "
                f"end stop) and H_0 > {self.G - reach:.3f} m, got H_0={self.H_0}, H_T={self.H_T}"
            )
        rpm = (self.omega_min * 30.0 / math.pi, self.omega_max * 30.0 / math.pi)
        # Friction, eq. (7): FMEP = c1 N^2 + c2 N + c3 (N in krpm) is a loss; a negative one is an engine
        # that makes torque without fuel. A quadratic's minimum on an interval: an end or its vertex.
        c1, c2, c3 = self.c_fr
        speeds = [n / 1000.0 for n in rpm]
        if c1 > 0 and speeds[0] < -c2 / (2 * c1) < speeds[1]:
            speeds.append(-c2 / (2 * c1))
        n_low = min(speeds, key=lambda n: (c1 * n + c2) * n + c3)
        if (c1 * n_low + c2) * n_low + c3 < 0.0:
            raise ValueError(
                f"LoaderParams.c_fr gives a negative friction (FMEP = {(c1 * n_low + c2) * n_low + c3:.3g} bar at "
                f"{1000 * n_low:.0f} rpm); FMEP = c1 N^2 + c2 N + c3 must be >= 0 between omega_min and omega_max, "
                f"got c_fr={self.c_fr}"
            )
        # Torque limit, eq. (31): the lowest line; a minimum of lines is concave, lowest at an end.
        for n in rpm:
            limit = min(a + b * n for a, b in self.T_max_lines)
            if not limit > 0.0:
                raise ValueError(
                    f"LoaderParams.T_max_lines gives a torque limit of {limit:.3g} N m at {n:.0f} rpm; min(a + b N) "
                    f"must be > 0 between omega_min and omega_max, got T_max_lines={self.T_max_lines}"
                )
        # Lift geometry, eqs. (11)-(13): the cylinder (frame point x_c, y_c; boom point at r1) must have a
        # positive moment arm wherever the bucket goes (H_0 up to the end stop), else k(theta2) diverges.
        r = self.r1 + self.r2
        s0 = max(-0.98, (self.H_0 - self.G) / r)
        for i in range(41):
            s = s0 + (0.98 - s0) * i / 40
            c = math.sqrt(1.0 - s * s)
            length = math.hypot(self.r1 * c - self.x_c, self.r1 * s - self.y_c)
            arm = self.r1 * (self.x_c * s - self.y_c * c) / length if length > 0 else 0.0
            if not arm > 1e-3 * self.r1:
                raise ValueError(
                    f"LoaderParams.x_c, y_c: the lift cylinder from ({self.x_c}, {self.y_c}) to the boom at r1 = "
                    f"{self.r1} m has no positive moment arm at H = {self.G + s * r:.2f} m; it must lift the boom "
                    f"for all heights from H_0 to the end stop G + 0.98 (r1 + r2)"
                )

    # ---- variants and serialization ----
    def replace(self, **changes: Any) -> LoaderParams:
        """A copy with some fields changed (validated). Unknown names raise ``ValueError``. ``distance`` sets
        both legs (``reverse_distance`` and ``forward_distance``), as the paper's 6.6 m each way; it cannot be given
        with either leg."""
        if "distance" in changes:
            both = changes.pop("distance")
            legs = sorted({"reverse_distance", "forward_distance"} & set(changes))
            if legs:  # which one wins would be a guess
                raise ValueError(f"give either distance or {' and '.join(legs)}, not both")
            changes["reverse_distance"] = changes["forward_distance"] = both
        known = {f.name for f in dataclasses.fields(self) if f.init}
        unknown = set(changes) - known
        if unknown:
            raise ValueError(f"unknown LoaderParams field(s): {shown(sorted(unknown), 200)}; known: {sorted(known)}")
        return dataclasses.replace(self, **changes)

    def variant(self, *, payload_scale: float = 1.0, rolling_scale: float = 1.0, **changes: Any) -> LoaderParams:
        """A variant for robustness studies: scale the payload M_load and the rolling coefficient c_r."""
        for name, scale in (("payload_scale", payload_scale), ("rolling_scale", rolling_scale)):
            if isinstance(scale, bool) or not isinstance(scale, numbers.Real) or not (is_finite(scale) and scale >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {shown(scale)}")
        changes.setdefault("M_load", self.M_load * payload_scale)
        changes.setdefault("c_r", self.c_r * rolling_scale)
        return self.replace(**changes)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LoaderParams:
        if not isinstance(data, dict):
            raise ValueError(f"parameter overrides must be a mapping of field -> value, got {type(data).__name__}")
        bad = [k for k in data if not isinstance(k, str)]
        if bad:
            raise ValueError(f"LoaderParams field names must be strings, got {bad!r}")
        return cls().replace(**data)

    def fingerprint(self) -> str:
        """A short stable hash of the values: the cache key of results computed with these parameters."""
        import hashlib

        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def is_real_number(value: Any) -> bool:
    """A finite real number (numpy's scalars included), not a bool (True is an int to Python, not a number to a
    validator); an int too large for a float is not finite (:func:`is_finite`)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and is_finite(value)


def is_integer(value: Any) -> bool:
    """An integer (numpy's included), not a bool: 2.9 is not cut to 2, nor True taken as 1."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_flag(name: str, value: Any) -> bool:
    """A switch given as True or False (numpy's bool too), else ValueError naming ``name``: ``bool(value)`` took
    "no" as True."""
    flag = plain(value)
    if not isinstance(flag, bool):
        raise ValueError(f"{name} must be True or False, got {shown(value)}")
    return flag


def is_finite(value: Any) -> bool:
    """``math.isfinite`` that says False for an int too large for a float (10**400 from JSON) instead of
    raising OverflowError: a validator then reports the value out of range."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def plain(value: Any) -> Any:
    """A numpy scalar as the Python number it holds (np.float32(0.1) -> 0.1, np.bool_ -> bool, which number
    checks still refuse); anything else as it is. For arguments checked with ``isinstance(v, (int, float))``."""
    import numpy as np

    if isinstance(value, np.floating) and value.dtype.itemsize < 8 and np.isfinite(value):
        return float(str(value))  # (its shortest decimal: np.float32(0.015).item() is 0.01499..., under a range's 0.015)
    return value.item() if isinstance(value, np.generic) and value.dtype.kind in "biuf" else value


def shown(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters: an error quotes the bad value, not all 10 MB of it."""
    try:
        text = repr(value)
    except ValueError:  # an int of more than 4300 digits (sys.get_int_max_str_digits)
        text = f"<{type(value).__name__} of more digits than Python prints>"
    return text if len(text) <= limit else f"{text[:limit - 5]}...{text[-2:]}"


def _unit(name: str) -> str:
    unit = PROVENANCE.get(name, ("-",))[0]
    return "" if unit == "-" or len(unit) > 10 else f" {unit}"


def _number(name: str, value: Any, allowed: Range, unit: str = "") -> float:
    """A finite real number (no bool, no string) within ``allowed``, as a float."""
    # (a float32 as the decimal it prints: np.float32(0.01) was refused as under decel_max's 0.01, and 0.03 was
    # stored as 0.0299999993, another fingerprint than the default's)
    value = plain(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"LoaderParams.{name} must be a number in {allowed}{unit}, got {shown(value)} "
                         f"({type(value).__name__})")
    if not is_finite(value):
        raise ValueError(f"LoaderParams.{name} must be a finite number in {allowed}{unit}, got {shown(value)}")
    v = float(value) + 0.0  # (-0.0 as 0.0: it compares equal, and gave another fingerprint, another cache key)
    if v not in allowed:
        raise ValueError(f"LoaderParams.{name} must lie in {allowed}{unit}, got {shown(value)}")
    return v


def _sequence(name: str, value: Any, length: int, of: str) -> list[Any]:
    """A list or tuple (or 1-d array) of exactly ``length`` entries."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        # a numpy array, by entry (its scalars as plain() reads them: tolist() gives a float32's binary value)
        value = list(value) if getattr(value, "ndim", 0) >= 1 else value.tolist()
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"LoaderParams.{name} must be a list of {length} {of}, got {shown(value)} ({type(value).__name__})")
    if len(value) != length:
        raise ValueError(f"LoaderParams.{name} must be a list of {length} {of}, got {len(value)} entries: {shown(value)}")
    return list(value)


def _coerce(name: str, value: Any) -> Any:
    """A field's value checked for type, shape, finiteness and range, as the type the model uses."""
    if name in _INT_RANGES:
        allowed = _INT_RANGES[name]
        if not is_integer(value):
            raise ValueError(f"LoaderParams.{name} must be an integer in {allowed}, got {shown(value)} "
                             f"({type(value).__name__})")
        if int(value) not in allowed:
            raise ValueError(f"LoaderParams.{name} must lie in {allowed}, got {shown(value)}")
        return int(value)
    if name in _VECTORS:
        length, allowed = _VECTORS[name]
        entries = _sequence(name, value, length, "numbers")
        return tuple(_number(f"{name}[{i}]", v, allowed) for i, v in enumerate(entries))
    if name == "T_max_lines":
        lines = _sequence(name, value, 3, "[a, b] pairs (T_ice <= a + b*N_rpm)")
        out = []
        for i, line in enumerate(lines):
            a, b = _sequence(f"{name}[{i}]", line, 2, "numbers [a, b] (T_ice <= a + b*N_rpm)")
            out.append((_number(f"{name}[{i}][0]", a, _T_MAX_A, " N m"), _number(f"{name}[{i}][1]", b, _T_MAX_B, " N m/rpm")))
        return tuple(out)
    return _number(name, value, _REAL_RANGES[name], _unit(name))


DEFAULT_PARAMS = LoaderParams()


def resolve_machine(params: LoaderParams | dict | None) -> LoaderParams:
    """:func:`resolve` for a user's machine (an environment's): a :class:`ParamsView`, the vector env's and the
    NLPs' internal view, holds no validated values of its own and is refused."""
    if isinstance(params, ParamsView):
        raise ValueError("params must be a LoaderParams, a dict of overrides or None, got a ParamsView (an internal "
                         "view of per-loader or symbolic values)")
    return resolve(params)


def resolve(params: LoaderParams | dict | None) -> LoaderParams:
    """``None`` -> the defaults, a dict -> the defaults with those overrides, a LoaderParams (or a
    :class:`ParamsView`) -> itself."""
    if params is None:
        return DEFAULT_PARAMS
    if isinstance(params, (LoaderParams, ParamsView)):
        return params
    if isinstance(params, dict):
        return LoaderParams.from_dict(params)
    raise ValueError(f"params must be a LoaderParams, a dict of overrides or None, got {type(params).__name__}")


# The fields a scenario sets (wl_env.scenario): they may vary between the loaders of a batch, or be
# symbols of an NLP parametric in the scenario. The model reads them, and M_tot and F_roll derived from them.
SCENARIO_FIELDS = ("M_load", "c_r", "H_T", "H_0", "omega_0", "reverse_distance", "forward_distance")


def scenario_overrides(params: Any) -> list[str]:
    """The fields a ``params`` dict of overrides sets that a scenario also sets (beside a scenario they would be
    dropped without a word: the env and the command line refuse them, naming these). ``distance``, the alias
    of both legs (:meth:`LoaderParams.replace`), counts too: it was dropped beside a scenario."""
    return sorted(set(params) & {*SCENARIO_FIELDS, "distance"}) if isinstance(params, dict) else []


def check_no_overridden(params: Any, source: Any, name: str = "params", kept: tuple[str, ...] = ()) -> None:
    """A ``params`` dict that sets a field a scenario sets (payload, distances, ...) beside that scenario
    (``source``, a Scenario or Suite; None: none) would be dropped without a word: refused, naming the fields (as
    ``wl --params`` with ``--scenario``). ``kept``: fields the caller does take from ``params``."""
    overridden = [f for f in scenario_overrides(params) if f not in kept] if source is not None else []
    if overridden:
        raise ValueError(f"{name} sets {', '.join(overridden)}, which the scenario sets: give them in the scenario "
                         f"(a dict of Scenario fields) or leave the scenario out")

# loaders in one vector env (wl_env.vector_env; PPOConfig.num_envs): each holds its own state arrays and random
# generator (~2 kB); the training's 64 are far below, and a mistyped count (1e9) is refused by name instead of
# exhausting the memory
MAX_NUM_ENVS = 16384


class ParamsView:
    """A :class:`LoaderParams` whose scenario fields (:data:`SCENARIO_FIELDS`) hold other values: numpy
    arrays of shape (N,), one loader per entry (the vector env), or CasADi symbols (an NLP that takes the
    scenario as a parameter). The model reads it as it reads LoaderParams; every other field and derived
    constant is the base's. Not validated: its values come from validated LoaderParams or from a solver."""

    def __init__(self, base: LoaderParams, **values: Any) -> None:
        unknown = set(values) - set(SCENARIO_FIELDS)
        if unknown:
            raise ValueError(f"ParamsView overrides only {SCENARIO_FIELDS}, got {sorted(unknown)}")
        self.base = base
        self.values = {name: values.get(name, getattr(base, name)) for name in SCENARIO_FIELDS}

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in ("base", "values"):
            raise AttributeError(name)
        v = self.values
        if name in v:
            return v[name]
        b = self.base
        if name == "M_tot":  # eq. (27)
            return b.M_veh + v["M_load"] + 4.0 * b.J_w / b.r_w**2
        if name == "F_roll":  # eq. (25)
            return v["c_r"] * (b.M_veh + v["M_load"]) * b.g
        if name == "final_position":
            return v["forward_distance"] - v["reverse_distance"]
        if name in ("fingerprint", "replace", "variant", "to_dict"):
            raise AttributeError(f"a ParamsView has no {name}(): it is not one parameter set")
        return getattr(b, name)
