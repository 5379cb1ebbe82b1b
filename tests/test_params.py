import dataclasses
import math

import pytest

from wl_env.params import DEFAULT_PARAMS, PROVENANCE, LoaderParams, resolve


def test_defaults_match_the_specification():
    p = DEFAULT_PARAMS
    assert p.M_veh == 32000.0 and p.M_load == 10000.0 and p.r_w == 0.70
    assert p.tc_xi_poly[-1] == 406.2 and p.tc_kappa_poly[-1] == 675.4
    assert p.T_max_lines == ((8.0, 2.086), (2200.0, 0.0), (3855.0, -1.40))
    # derived constants of eqs. (17), (25), (27)
    assert p.A_piston == pytest.approx(2 * math.pi * (0.095**2 - 0.045**2))
    assert p.M_tot == pytest.approx(42000 + 4 * 1000 / 0.7**2)
    assert p.F_roll == pytest.approx(0.03 * 42000 * 9.81)


def test_every_field_has_provenance():
    names = {f.name for f in dataclasses.fields(LoaderParams) if f.init}
    assert names == set(PROVENANCE)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"M_veh": -1.0}, "M_veh"),
        ({"eta_gb": 1.2}, "eta_gb"),
        ({"eta_lift": 0.0}, "eta_lift"),
        ({"tc_xi_poly": (1.0, 2.0)}, "tc_xi_poly"),
        ({"c_fr": (1.0, 2.0, 3.0, 4.0)}, "c_fr"),
        ({"r_w": float("nan")}, "r_w"),
        ({"H_T": 9.0}, "H_T"),
        ({"omega_0": 300.0}, "omega_0"),
        ({"r_rod": 0.2}, "r_rod"),
    ],
)
def test_invalid_values_name_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        DEFAULT_PARAMS.replace(**change)


def test_unknown_field_is_rejected():
    with pytest.raises(ValueError, match="unknown LoaderParams field"):
        DEFAULT_PARAMS.replace(payload=3)


def test_variants_and_round_trip():
    heavy = DEFAULT_PARAMS.variant(payload_scale=1.2, rolling_scale=0.7)
    assert heavy.M_load == pytest.approx(12000.0) and heavy.c_r == pytest.approx(0.021)
    assert heavy.M_tot > DEFAULT_PARAMS.M_tot and heavy.fingerprint() != DEFAULT_PARAMS.fingerprint()
    assert LoaderParams.from_dict(heavy.to_dict()) == heavy
    assert resolve({"distance": 8.0}).distance == 8.0
    with pytest.raises(ValueError, match="params must be"):
        resolve(42)
