"""The stand-in broker's model: durations, times, Orion's syntax rules, service paths, change detection."""

import pytest

from tests.ngsi_broker import model


@pytest.mark.parametrize("text, seconds", [
    ("PT1S", 1), ("PT0.5S", 0.5), ("PT5M", 300), ("PT1H", 3600), ("PT24H", 86400), ("P1D", 86400),
    ("P1W", 7 * 86400), ("P1M", 30 * 86400), ("P1Y", 365 * 86400), ("P1DT2H30M", 86400 + 9000), ("PT0S", 0)])
def test_iso8601_durations(text, seconds):
    assert model.parse_duration(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["", "P", "PT", "1D", "P1H", "PT1D", "P1DT", "one day", None, 5])
def test_bad_durations(text):
    with pytest.raises(ValueError):
        model.parse_duration(text)


def test_times_render_as_orion_does():
    epoch = model.parse_iso_time("2040-01-01T14:00:00.00Z")
    assert model.iso_time(epoch) == "2040-01-01T14:00:00.000Z"
    assert model.parse_iso_time("2040-01-01T14:00:00") == epoch          # naive means UTC
    assert model.parse_iso_time("2040-01-01T15:00:00+01:00") == epoch
    assert model.iso_time(model.parse_iso_time("2040-01-01T14:00:00.123456Z")) == "2040-01-01T14:00:00.123Z"
    for bad in ("tomorrow", "", "2040-13-01"):
        with pytest.raises(ValueError):
            model.parse_iso_time(bad)


@pytest.mark.parametrize("value, bad", [
    ("plain text, with: {braces} [brackets] %27 & ? / #", False), ("a<b", True), ("a>b", True), ('"', True),
    ("'", True), ("a=b", True), ("a;b", True), ("f(x)", True), (12, False), (None, False), (True, False),
    ({"k": ["ok", {"deep": "x)"}]}, True), ({"k(": "v"}, True), (["ok", 1, {"a": "b"}], False)])
def test_forbidden_characters_in_values(value, bad):
    assert model.value_has_forbidden_chars(value) is bad


@pytest.mark.parametrize("identifier, ok", [
    ("robot1", True), ("move_base.goal", True), ("std_msgs.msg.String", True), ("a-b:c", True),
    ("a b", False), ("a/b", False), ("a#b", False), ("a?b", False), ("a&b", False), ("a=b", False),
    ("tab\there", False), ("ñ", False), ("", False), ("x" * 256, True), ("x" * 257, False)])
def test_identifier_rules(identifier, ok):
    if ok:
        assert model.check_identifier(identifier, "entity id") == identifier
    else:
        with pytest.raises(model.NgsiError) as caught:
            model.check_identifier(identifier, "entity id")
        assert caught.value.status == 400 and caught.value.error == "BadRequest"


def test_service_paths():
    assert model.parse_update_service_path(None) == "/"
    assert model.parse_update_service_path("/robots/") == "/robots"
    assert model.parse_query_service_paths(None) == [("/", True)]
    assert model.parse_query_service_paths("/a/#, /b") == [("/a", True), ("/b", False)]
    assert model.service_path_matches("/a/b", [("/a", True)])
    assert not model.service_path_matches("/ab", [("/a", True)])
    assert not model.service_path_matches("/a/b", [("/a", False)])
    for bad in ("relative", "/a b", "/" + "/".join("x" * 11), "/" + "x" * 51):
        with pytest.raises(model.NgsiError):
            model.parse_query_service_paths(bad)
    for bad in ("/a,/b", "/a/#"):
        with pytest.raises(model.NgsiError):
            model.parse_update_service_path(bad)
    assert model.parse_tenant("MyService") == "myservice"
    assert model.parse_tenant(None) == model.parse_tenant("") == ""
    with pytest.raises(model.NgsiError):
        model.parse_tenant("my-service")


def test_only_real_changes_count():
    entity = model.Entity("r1", "ROBOT", "/")

    def attr(value, attr_type="T", metadata=None):
        return {"type": attr_type, "value": value, "metadata": metadata or {}}

    assert model.set_attributes(entity, {"a": attr(1), "b": attr("x")}) == ["a", "b"]
    assert model.set_attributes(entity, {"a": attr(1), "b": attr("x")}) == []
    assert model.set_attributes(entity, {"a": attr(1.0)}) == ["a"]           # 1 and 1.0 differ in JSON
    assert model.set_attributes(entity, {"a": attr(1.0, "U")}) == ["a"]       # type change
    assert model.set_attributes(entity, {"a": attr(1.0, "U", {"m": {"type": "T", "value": 1}})}) == ["a"]
    assert model.set_attributes(entity, {"c": attr(True)}, replace=True) == ["c"]
    assert list(entity.attrs) == ["c"]
