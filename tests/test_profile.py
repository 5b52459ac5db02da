import copy

import pytest
from pydantic import ValidationError

from hapticd.profile import ProfileError, load_profile, parse_profile
from tests.conftest import GRASP_PROFILE


def test_bundled_profile_loads_with_si_values():
    p = load_profile(GRASP_PROFILE)
    assert p.finger_names == ("thumb", "index")
    assert p.scene.object.stiffness_n_per_m == 60.0
    assert p.rendering.allocator == "if"
    assert p.rendering.actuation_frame == "grasp"
    assert p.loop.rate_hz == 1000.0
    assert p.source == GRASP_PROFILE.resolve()


def test_profile_is_frozen():
    p = load_profile(GRASP_PROFILE)
    with pytest.raises(ValidationError):
        p.safety.max_force_n = 100.0  # type: ignore[misc]


def test_misspelled_key_is_named_with_a_suggestion(grasp_data, write_profile):
    obj = grasp_data["scene"]["object"]
    obj["stifness_n_per_m"] = obj.pop("stiffness_n_per_m")
    path = write_profile(grasp_data)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert str(path.resolve()) in msg
    assert "scene.object.stifness_n_per_m: unknown key; did you mean 'stiffness_n_per_m'?" in msg
    assert "scene.object.stiffness_n_per_m: required key is missing" in msg


def test_a_key_of_another_section_is_not_suggested_as_its_own_fix(grasp_data, write_profile):
    """'trajectory' is a key of the replay backend, not of dhd: the message says so, it does
    not ask "did you mean 'trajectory'?"."""
    grasp_data["fingers"][0]["device"]["backend"] = "dhd"
    path = write_profile(grasp_data)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert "fingers[0:thumb].device.trajectory: unknown key: the dhd backend has no key" in msg
    assert "did you mean 'trajectory'" not in msg
    # A section that is not a backend's says "this section".
    grasp_data["fingers"][0]["device"]["backend"] = "replay"
    grasp_data["scene"]["object"]["rate_hz"] = 1000
    with pytest.raises(ProfileError, match=r"scene.object.rate_hz: unknown key: this section"):
        load_profile(write_profile(grasp_data))


@pytest.mark.parametrize(
    ("mutate", "where", "what"),
    [
        (
            lambda d: d["fingers"][0].__setitem__("actuated_directions", [[1, 1, 0]]),
            "fingers[0:thumb].actuated_directions",
            "unit vector",
        ),
        (
            lambda d: d["fingers"][1]["device"].__setitem__("max_force_n", -2),
            "fingers[1:index].device.max_force_n",
            "greater than 0",
        ),
        (
            lambda d: d["loop"].__setitem__("rate_hz", 20000),
            "loop.rate_hz",
            "less than or equal to 8000",
        ),
        (
            lambda d: d["rendering"].__setitem__("allocator", "magic"),
            "rendering.allocator",
            "'adaptive', 'pinv_exact'",
        ),
        (
            lambda d: d["scene"]["object"].__setitem__("size_m", [0.05, -1, 0.05]),
            "scene.object.size_m",
            "(0, 1]",
        ),
        (
            lambda d: d["fingers"][0]["device"].__setitem__("backend", "teleport"),
            "fingers[0:thumb].device",
            "replay",
        ),
        (lambda d: d["fingers"][1].__setitem__("name", "thumb"), "fingers", "unique"),
        (lambda d: d.pop("safety"), "safety", "missing"),
        (
            lambda d: d["fingers"][0].__setitem__("actuated_directions", [[1, 0, 0]] * 4),
            "fingers[0:thumb].actuated_directions",
            "at most 3",
        ),
    ],
)
def test_bad_values_name_key_and_expectation(grasp_data, mutate, where, what):
    data = copy.deepcopy(grasp_data)
    mutate(data)
    with pytest.raises(ProfileError) as exc:
        parse_profile(data, "p.yaml")
    msg = str(exc.value)
    assert msg.startswith("p.yaml:")
    line = next((ln for ln in msg.splitlines() if ln.strip().startswith(where)), None)
    assert line is not None, msg
    assert what in line, msg


def test_grasp_frame_needs_two_fingers(grasp_data):
    grasp_data["fingers"] = grasp_data["fingers"][:1]
    with pytest.raises(ProfileError, match="grasp' needs at least two fingers"):
        parse_profile(grasp_data, "p.yaml")


def test_invalid_yaml_reports_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nfingers: [\n  - {a: 1\n")
    with pytest.raises(ProfileError, match=r"bad.yaml: not valid YAML at line \d+"):
        load_profile(path)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ProfileError, match="cannot read profile"):
        load_profile(tmp_path / "nope.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ProfileError, match="expected a mapping"):
        load_profile(tmp_path / "list.yaml")


def test_directions_are_normalised(grasp_data):
    grasp_data["fingers"][0]["actuated_directions"] = [[0.8660254, 0.0, 0.5]]
    p = parse_profile(grasp_data, "p.yaml")
    d = p.fingers[0].actuated_directions[0]
    assert abs(sum(c * c for c in d) - 1.0) < 1e-15
