import pytest

from hvac_mpc.contract import InvalidReference, Reference


def test_valid_reference_and_split():
    r = Reference.from_split(18.0, 0.03, (2, 1, 1))
    assert r.split == pytest.approx((0.015, 0.0075, 0.0075))
    assert Reference(20.0, 0.02).split is None


@pytest.mark.parametrize("data, field", [
    ({"supply_temp_c": 80.0, "volume_flow_m3s": 0.03}, "supply_temp_c"),
    ({"supply_temp_c": 20.0, "volume_flow_m3s": 0.5}, "volume_flow_m3s"),
    ({"supply_temp_c": "warm", "volume_flow_m3s": 0.03}, "supply_temp_c"),
    ({"supply_temp_c": float("nan"), "volume_flow_m3s": 0.03}, "supply_temp_c"),
    ({"supply_temp_c": True, "volume_flow_m3s": 0.03}, "supply_temp_c"),
    ({"volume_flow_m3s": 0.03}, "supply_temp_c"),
    ({"supply_temp_c": 20.0, "volume_flow_m3s": 0.03, "flow_m_m3s": 0.01}, "flow_f_m3s"),
    ({"supply_temp_c": 20.0, "volume_flow_m3s": 0.03, "flow_m_m3s": 0.03, "flow_f_m3s": 0.02,
      "flow_w_m3s": 0.01}, "volume_flow_m3s"),
    ({"supply_temp_c": 20.0, "volume_flow_m3s": 0.03, "heat": 1}, "heat"),
])
def test_bad_reference_names_the_field_and_range(data, field):
    with pytest.raises(InvalidReference, match=field):
        Reference.from_mapping(data)


def test_out_of_range_message_gives_the_range():
    with pytest.raises(InvalidReference, match=r"\[5.0, 50.0\]"):
        Reference(60.0, 0.03)
