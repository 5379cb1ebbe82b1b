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
    "omega_0": ("rad/s", "paper Table II (1500 rpm)"),
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
    "distance": ("m", "paper (each way)"),
}

_POSITIVE = (
    "g J_ice q_hv n_cyl V_d U_mf_max omega_min omega_max omega_0 tc_phi_hi gear_ratio r_w J_w M_veh "
    "M_boom I_boom r1 r2 n_lift_cyl r_piston r_rod P_cyl_max D_pump pump_speed_sat U_b_max V_max "
    "decel_max H_T distance"
).split()
_NONNEGATIVE = ("M_load", "c_r", "H_0", "G")
_EFFICIENCIES = ("eta_ig", "eta_gb", "eta_lift", "eta_vol", "eta_cyl")


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
    omega_0: float = 157.08
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
    distance: float = 6.6

    # ---- derived constants (cached so hot paths do not recompute them) ----
    _derived: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Accept lists (e.g. from JSON) and store tuples so the instance stays hashable.
        for name in ("c_fr", "tc_xi_poly", "tc_kappa_poly", "U_ab_bounds"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        object.__setattr__(self, "T_max_lines", tuple(tuple(float(v) for v in line) for line in self.T_max_lines))
        self._validate()
        d = self._derived
        d["r"] = self.r1 + self.r2
        d["A_piston"] = self.n_lift_cyl * math.pi * (self.r_piston**2 - self.r_rod**2)
        d["M_tot"] = self.M_veh + self.M_load + 4.0 * self.J_w / self.r_w**2
        d["F_roll"] = self.c_r * (self.M_veh + self.M_load) * self.g
        d["T_ig_per_mg"] = self.eta_ig * self.q_hv * self.n_cyl * 1e-6 / (4.0 * math.pi)
        d["T_fric_scale"] = self.V_d * 1e5 / (4.0 * math.pi)
        d["fuel_per_mg_rad"] = 1e-6 * self.n_cyl / (4.0 * math.pi)
        from wl_env.physics.torque_converter import polynomial_extension  # (physics imports params)

        d["xi_ext"] = polynomial_extension(self.tc_xi_poly, self.tc_phi_hi)
        d["kappa_ext"] = polynomial_extension(self.tc_kappa_poly, self.tc_phi_hi)

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
    def H_max(self) -> float:
        """Highest reachable bucket height G + r (m): the boom vertical."""
        return self.G + self.r

    def _validate(self) -> None:
        for name in _POSITIVE:
            _check_finite(name, getattr(self, name))
            if not getattr(self, name) > 0:
                raise ValueError(f"LoaderParams.{name} must be > 0, got {getattr(self, name)!r}")
        for name in _NONNEGATIVE:
            _check_finite(name, getattr(self, name))
            if getattr(self, name) < 0:
                raise ValueError(f"LoaderParams.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in _EFFICIENCIES:
            v = getattr(self, name)
            _check_finite(name, v)
            if not 0.0 < v <= 1.0:
                raise ValueError(f"LoaderParams.{name} is an efficiency and must lie in (0, 1], got {v!r}")
        for name in ("x_c", "y_c"):
            _check_finite(name, getattr(self, name))
        if len(self.c_fr) != 3:
            raise ValueError(f"LoaderParams.c_fr needs 3 coefficients (c_fr1..3), got {len(self.c_fr)}")
        for name in ("tc_xi_poly", "tc_kappa_poly"):
            poly = getattr(self, name)
            if len(poly) != 7:
                raise ValueError(f"LoaderParams.{name} needs 7 coefficients (6th order, highest first), got {len(poly)}")
            for v in poly:
                _check_finite(name, v)
        if len(self.T_max_lines) != 3 or any(len(line) != 2 for line in self.T_max_lines):
            raise ValueError("LoaderParams.T_max_lines needs three [a, b] pairs (T_ice <= a + b*N_rpm)")
        lo, hi = self.U_ab_bounds
        if not (len(self.U_ab_bounds) == 2 and lo < 0.0 < hi):
            raise ValueError(f"LoaderParams.U_ab_bounds must be (lo, hi) with lo < 0 < hi, got {self.U_ab_bounds}")
        if not self.omega_min < self.omega_0 < self.omega_max:
            raise ValueError(
                f"LoaderParams.omega_0 must lie in (omega_min, omega_max) = ({self.omega_min}, {self.omega_max}), "
                f"got {self.omega_0}"
            )
        if self.r_rod >= self.r_piston:
            raise ValueError(f"LoaderParams.r_rod must be < r_piston ({self.r_piston}), got {self.r_rod}")
        reach = 0.98 * (self.r1 + self.r2)  # the boom's end stops, wl_env.physics.lift.BOOM_SIN_MAX
        if not self.G - reach < self.H_0 < self.H_T < self.G + reach:
            raise ValueError(
                f"LoaderParams.H_T must satisfy H_0 < H_T < {self.G + reach:.3f} m (G + 0.98 (r1 + r2), the boom's "
                f"end stop) and H_0 > {self.G - reach:.3f} m, got H_0={self.H_0}, H_T={self.H_T}"
            )

    # ---- variants and serialization ----
    def replace(self, **changes: Any) -> LoaderParams:
        """A copy with some fields changed (validated). Unknown names raise ``ValueError``."""
        known = {f.name for f in dataclasses.fields(self) if f.init}
        unknown = set(changes) - known
        if unknown:
            raise ValueError(f"unknown LoaderParams field(s): {sorted(unknown)}; known: {sorted(known)}")
        return dataclasses.replace(self, **changes)

    def variant(self, *, payload_scale: float = 1.0, rolling_scale: float = 1.0, **changes: Any) -> LoaderParams:
        """A variant for robustness studies: scale the payload M_load and the rolling coefficient c_r."""
        if not (math.isfinite(payload_scale) and payload_scale >= 0):
            raise ValueError(f"payload_scale must be a finite number >= 0, got {payload_scale!r}")
        if not (math.isfinite(rolling_scale) and rolling_scale >= 0):
            raise ValueError(f"rolling_scale must be a finite number >= 0, got {rolling_scale!r}")
        changes.setdefault("M_load", self.M_load * payload_scale)
        changes.setdefault("c_r", self.c_r * rolling_scale)
        return self.replace(**changes)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LoaderParams:
        if not isinstance(data, dict):
            raise ValueError(f"parameter overrides must be a mapping of field -> value, got {type(data).__name__}")
        return cls().replace(**data)

    def fingerprint(self) -> str:
        """A short stable hash of the values: the cache key of results computed with these parameters."""
        import hashlib

        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _check_finite(name: str, value: Any) -> None:
    try:
        ok = math.isfinite(float(value))
    except (TypeError, ValueError):
        raise ValueError(f"LoaderParams.{name} must be a number, got {value!r}") from None
    if not ok:
        raise ValueError(f"LoaderParams.{name} must be finite, got {value!r}")


DEFAULT_PARAMS = LoaderParams()


def resolve(params: LoaderParams | dict | None) -> LoaderParams:
    """``None`` -> the defaults, a dict -> the defaults with those overrides, a LoaderParams -> itself."""
    if params is None:
        return DEFAULT_PARAMS
    if isinstance(params, LoaderParams):
        return params
    if isinstance(params, dict):
        return LoaderParams.from_dict(params)
    raise ValueError(f"params must be a LoaderParams, a dict of overrides or None, got {type(params).__name__}")
