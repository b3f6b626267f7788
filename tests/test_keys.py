"""The key scheme: every key dyknow uses is built by dyknow.keys, and taken apart by it."""

from __future__ import annotations

import pytest

from dyknow import UnitError, keys
from dyknow.transport import check_key_expr, key_exprs_intersect

LAYOUT = [
    (keys.default_key("robot", "cam", "out"), "dyknow/robot/cam/out"),
    (keys.unit_prefix("robot", "cam"), "dyknow/robot/cam/"),
    (keys.request_key("robot", "BallTrack(field)"), "dyknow/robot/requests/BallTrack(field)"),
    (keys.request_key("robot", "A(b c)/d*e$f?g#h@i"), "dyknow/robot/requests/A(b_c)_d_e_f_g_h_i"),
    (keys.event_key("robot", "adaptation"), "dyknow/robot/events/adaptation"),
    (keys.measurement_key("battery"), "dyknow/measurements/battery"),
    (keys.measurement_key("battery", "robot"), "dyknow/robot/measurements/battery"),
    (keys.manager_service_key("robot", "spawn"), "@dyknow/robot/spawn"),
    (keys.unit_service_key("robot", "cam", "get_config"), "@dyknow/robot/unit/cam/get_config"),
    (keys.services_pattern("robot"), "@dyknow/robot/**"),
    (keys.port_token("dyknow/robot/cam/out"), "dyknow/robot/cam/out"),
]


@pytest.mark.parametrize(("built", "expected"), LAYOUT)
def test_the_layout(built: str, expected: str) -> None:
    assert built == expected


def test_every_built_key_is_a_valid_key_expression() -> None:
    for built, _ in LAYOUT:
        check_key_expr(built.rstrip("/"))


def test_data_subscriptions_never_reach_services() -> None:
    for data_pattern in ("**", "dyknow/**", "*/robot/**"):
        assert not key_exprs_intersect(data_pattern, keys.manager_service_key("robot", "spawn"))
    assert key_exprs_intersect(keys.services_pattern("robot"), keys.unit_service_key("robot", "cam", "set_config"))


def test_a_manager_takes_measurements_for_all_and_for_itself() -> None:
    every, own = keys.measurement_patterns("robot")
    assert key_exprs_intersect(every, keys.measurement_key("battery"))
    assert key_exprs_intersect(own, keys.measurement_key("battery", "robot"))
    assert not key_exprs_intersect(own, keys.measurement_key("battery", "ground"))


@pytest.mark.parametrize(
    ("key", "service", "unit"),
    [
        ("@dyknow/robot/spawn", "spawn", None),
        ("@dyknow/robot/unit/cam/get_config", "get_config", "cam"),
        ("@dyknow/robot/unit/cam", None, None),
        ("@dyknow/robot/", None, None),
        ("@dyknow/ground/spawn", None, None),
        ("dyknow/robot/spawn", None, None),
        ("@dyknow/robot/unit//get_config", None, None),
    ],
)
def test_service_keys_are_taken_apart(key: str, service: str | None, unit: str | None) -> None:
    address = keys.parse_service_key("robot", key)
    if service is None:
        assert address is None
    else:
        assert address == keys.ServiceAddress(service, unit)


@pytest.mark.parametrize("name", ["robot", "cam_1", "cam-1", "a.b", "0", "_x"])
def test_valid_names(name: str) -> None:
    assert keys.check_name(name, "unit name") == name


@pytest.mark.parametrize("name", ["", "-a", ".a", "a/b", "a*", "a b", "a$", "a@b", 3, None])
def test_invalid_names(name: object) -> None:
    with pytest.raises(UnitError, match="is not a valid name"):
        keys.check_name(name, "unit name")


@pytest.mark.parametrize(
    ("token", "manager"),
    [
        ("@dyknow/robot", "robot"),
        ("@dyknow/cam-1.b_2", "cam-1.b_2"),
        ("@dyknow/robot/get_model", None),  # a service, not a token
        ("dyknow/robot", None),
        ("@dyknow/", None),
        # anyone may declare @dyknow/<any text>: no manager has such a name, so none is listed
        ("@dyknow/\x1b]0;pwned\x07", None),
        ("@dyknow/\x1b[2J", None),
        ("@dyknow/evil\u202etxt", None),
        ("@dyknow/a b", None),
        ("@dyknow/-a", None),
        (f"@dyknow/{'m' * 129}", None),  # longer than MAX_NAME_BYTES
    ],
)
def test_a_token_names_a_manager_only_by_a_manager_name(token: str, manager: str | None) -> None:
    assert keys.manager_of_token(token) == manager


# ---------------------------------------------------------------------- key expressions matching keys

_CHUNKS = ["a", "b", "ab", "robot", "requests", "Secret(vault)", "@dyknow", "@x", "x1"]
_PARTS = [*_CHUNKS, "*", "**", "a$*", "$*b", "r$*s", "$*"]


def _zenoh_includes(key_expr: str, key: str) -> bool:
    import zenoh  # the independent implementation: Zenoh's own (Rust) key expressions

    return bool(zenoh.KeyExpr.autocanonize(key_expr).includes(zenoh.KeyExpr(key)))


def _canonical(parts: list[str]) -> bool:
    """Whether Zenoh takes this pattern as written (no '**/**', no '**/*': it canonises those)."""
    text = "/".join(parts)
    import zenoh

    try:
        return str(zenoh.KeyExpr(text)) == text
    except zenoh.ZError:
        return False


@pytest.mark.parametrize(
    ("key_expr", "key", "expected"),
    [
        ("dyknow/**", "dyknow/robot/requests/Secret(vault)", True),
        ("dyknow/robot/monitors/**", "dyknow/robot/requests/Secret(vault)", False),
        ("dyknow/*/requests/*", "dyknow/robot/requests/Secret(vault)", True),
        ("dyknow/**/Secret$*", "dyknow/robot/requests/Secret(vault)", True),
        ("**", "@dyknow/robot/spawn", False),
        ("@dyknow/**", "@dyknow/robot/spawn", True),
        ("dyknow/robot/**", "dyknow/robot", True),
    ],
)
def test_a_key_expression_includes_a_key(key_expr: str, key: str, expected: bool) -> None:
    assert keys.includes(key_expr, key) is expected is _zenoh_includes(key_expr, key)


def test_includes_agrees_with_zenoh_on_random_patterns() -> None:
    """keys.includes (the ACL's data rights use it) against Zenoh's own matching, on every
    pattern of up to 4 parts and keys of up to 4 chunks drawn from a mix of plain, verbatim and
    wildcard chunks."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=3000, deadline=None, derandomize=True)
    @given(st.lists(st.sampled_from(_PARTS), min_size=1, max_size=4), st.lists(st.sampled_from(_CHUNKS), min_size=1, max_size=4))
    def agree(parts: list[str], chunks: list[str]) -> None:
        if not _canonical(parts):
            return
        key_expr, key = "/".join(parts), "/".join(chunks)
        assert keys.includes(key_expr, key) == _zenoh_includes(key_expr, key), (key_expr, key)

    agree()


def test_offer_tokens_name_their_manager_and_a_glob_asks_zenoh_for_no_less_than_fnmatch() -> None:
    """Offer tokens (issue 40): functor and arguments by chunk, unsafe characters as '_', the
    manager last; a manager glob's key expression matches every token whose name fnmatch accepts."""
    import fnmatch

    assert keys.offer_token("BallTrack", ("field",), "robot") == "@dyknow/offers/BallTrack/(field)/robot"
    assert keys.offer_token("Battery", (), "robot") == "@dyknow/offers/Battery/()/robot"
    assert keys.offer_token("A/B*", ("x y", "z"), "m") == "@dyknow/offers/A_B_/(x_y,z)/m"
    for functor, args in [("A/B*", ("x y", "z")), ("T$x", ("#", "?")), ("", ())]:
        check_key_expr(keys.offer_token(functor, args, "m"), what="offer", concrete=True)  # Zenoh takes it
    assert keys.manager_of_offer(keys.offer_token("T", ("a",), "m-1")) == "m-1"
    assert keys.manager_of_offer("@dyknow/offers/T/(a)/*") is None and keys.manager_of_offer("@dyknow/m-1") is None
    assert keys.includes(keys.offers_pattern("T", ("a",)), keys.offer_token("T", ("a",), "m"))
    assert not keys.includes(keys.offers_pattern("T", ("a",)), keys.offer_token("T", ("b",), "m"))
    assert keys.includes(keys.offers_of("m"), keys.offer_token("T", ("a", "b"), "m"))
    names = ["robot", "robot-1", "robot-12", "rob", "station", "r", "robot.x", "xrobot", "a-b-c"]
    for glob in ["*", "robot*", "robot-*", "r*t", "*o*", "rob?t", "robot-[12]*", "a*b*c", "station", "?"]:
        pattern = keys.managers_matching(glob)
        for name in names:
            if fnmatch.fnmatchcase(name, glob):
                assert keys.includes(pattern, keys.manager_token(name)), (glob, name, pattern)
                assert key_exprs_intersect(pattern, keys.manager_token(name)), (glob, name, pattern)  # as Zenoh matches them
        check_key_expr(pattern, what="glob")
    with pytest.raises(UnitError, match="cannot match a manager name"):
        keys.managers_matching("a/b")
