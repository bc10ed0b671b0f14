"""The optional light schedule of a scenario: the light level changes at given times (the dark lap of
office_loop); the episode's ``light`` override still wins; bad schedules are refused by name."""
import pytest

from sim.scenario import ScenarioError, load_scenario


def test_office_loop_goes_dark_for_its_last_lap():
    from sim.episode import Episode

    sc = load_scenario("office_loop")
    assert sc.light == 1.0 and sc.light_schedule == [[157.0, 0.0]]
    with Episode(sc, duration=0.1, camera=False, lidar=False) as ep:
        assert ep.light_at(0.0) == 1.0 and ep.light_at(156.9) == 1.0
        assert ep.light_at(157.0) == 0.0 and ep.light_at(240.0) == 0.0
    with Episode(sc, duration=0.1, light=0.5, camera=False, lidar=False) as ep:  # an explicit light wins
        assert ep.light_at(0.0) == 0.5 and ep.light_at(200.0) == 0.5
    assert load_scenario("office_loop_twice").light_schedule == []  # its own, lit throughout


@pytest.mark.parametrize("schedule, entry", [("[[10.0, 0.0], [5.0, 1.0]]", 1), ("[[10.0, 1.5]]", 0),
                                             ("[[-1.0, 0.0]]", 0)])
def test_bad_light_schedules_are_named(tmp_path, schedule, entry):
    text = open(load_scenario("office_loop").source).read()
    assert "light_schedule = [[157.0, 0.0]]" in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace("light_schedule = [[157.0, 0.0]]", f"light_schedule = {schedule}"))
    with pytest.raises(ScenarioError, match=rf"bad.toml: .*light_schedule.{entry}: expected \[time s >= 0, "
                                            rf"increasing; level 0..1\]"):
        load_scenario(path)
