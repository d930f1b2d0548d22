"""Station settings: one TOML file, every key an environment variable, every key checked first."""

from pathlib import Path

import pytest

from eol_cal.errors import InputError
from eol_cal.station.settings import KEYS, MODBUS_PORT, check_station, env_name, load_settings

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"

GOOD = """\
station_id = "L3-EOL-02"
limits = "limits.toml"
variant = "EPS-STD"
db = "records.sqlite"
key_file = "ecu.key"
[dyno]
address = "127.0.0.1"
[can]
interface = "virtual"
channel = "eol"
"""


@pytest.fixture
def station_dir(tmp_path: Path) -> Path:
    (tmp_path / "ecu.key").write_text("000102030405060708090a0b0c0d0e0f\n")
    (tmp_path / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    (tmp_path / "station.toml").write_text(GOOD)
    return tmp_path


def _refused(path, env=None, check=False) -> InputError:
    with pytest.raises(InputError) as info:
        s = load_settings(path, env or {})
        if check:
            check_station(s)
    return info.value


def test_good_file_loads_with_defaults_and_paths_beside_it(station_dir: Path) -> None:
    s = load_settings(station_dir / "station.toml", {})
    check_station(s)
    assert (s.dyno_host, s.dyno_port) == ("127.0.0.1", MODBUS_PORT)
    assert s.path("limits") == (station_dir / "limits.toml").resolve()
    assert s["profile"] == "eol-default" and s.origin["profile"] == "default"
    assert s.origin["station_id"] == "file"


def test_environment_overrides_each_key(station_dir: Path) -> None:
    env = {env_name("dyno.address"): "10.1.2.3:1502", env_name("rate_hz"): "20000", env_name("station_id"): "L9"}
    s = load_settings(station_dir / "station.toml", env)
    assert (s.dyno_host, s.dyno_port, s["rate_hz"], s["station_id"]) == ("10.1.2.3", 1502, 20000, "L9")
    assert s.origin["rate_hz"] == "env"


def test_the_dyno_watchdog_is_a_setting_the_cycle_uses(station_dir: Path) -> None:
    from eol_cal.station.configure import station_config

    s = load_settings(station_dir / "station.toml", {})
    assert s["dyno.watchdog_ms"] == 2000 and s.origin["dyno.watchdog_ms"] == "default"
    s = load_settings(station_dir / "station.toml", {env_name("dyno.watchdog_ms"): "5000"})
    assert s["dyno.watchdog_ms"] == 5000
    with pytest.raises(InputError, match="dyno.watchdog_ms"):
        load_settings(station_dir / "station.toml", {env_name("dyno.watchdog_ms"): "70000"})
    assert station_config(s).dyno.watchdog_ms == 5000


def test_the_read_back_is_a_setting_the_cycle_uses(station_dir: Path) -> None:
    from eol_cal.station.configure import station_config

    s = load_settings(station_dir / "station.toml", {})
    assert s["flash.read_back"] == "before-crc" and station_config(s).read_back is True
    s = load_settings(station_dir / "station.toml", {env_name("flash.read_back"): "off"})
    assert station_config(s).read_back is False
    with pytest.raises(InputError, match="flash.read_back.*'after' is not one of before-crc, off"):
        load_settings(station_dir / "station.toml", {env_name("flash.read_back"): "after"})
    # `eol-cal run --read-back` offers the same choices (the CLI does not import the settings module)
    from cli.station import OPTION_KEYS, run_cmd
    from eol_cal.station.settings import READ_BACK_CHOICES

    (option,) = [p for p in run_cmd.params if p.name == "read_back"]
    assert tuple(option.type.choices) == READ_BACK_CHOICES and OPTION_KEYS["read_back"] == "flash.read_back"


def test_the_lead_in_is_a_setting_the_cycle_uses(station_dir: Path) -> None:
    from cli.station import OPTION_KEYS, run_cmd
    from eol_cal.station.configure import station_config
    from eol_cal.station.settings import LEAD_IN_CHOICES

    s = load_settings(station_dir / "station.toml", {})
    assert s["dyno.lead_in"] == "settle" and station_config(s).lead_in == "settle"
    for choice in ("at-point", "off"):
        s = load_settings(station_dir / "station.toml", {env_name("dyno.lead_in"): choice})
        assert station_config(s).lead_in == choice
    with pytest.raises(InputError, match="dyno.lead_in.*'0' is not one of settle, at-point, off"):
        load_settings(station_dir / "station.toml", {env_name("dyno.lead_in"): "0"})
    (option,) = [p for p in run_cmd.params if p.name == "lead_in"]
    assert tuple(option.type.choices) == LEAD_IN_CHOICES and OPTION_KEYS["lead_in"] == "dyno.lead_in"


def test_every_key_has_its_own_variable() -> None:
    names = [env_name(k.name) for k in KEYS]
    assert len(set(names)) == len(names)
    assert "EOL_CAL_CAN_BITRATE" in names


@pytest.mark.parametrize("edit, key, words", [
    ('station_id = "L3-EOL-02"', "station_id", "required"),
    ('[dyno]\naddress = "127.0.0.1"', "dyno.address", "required"),
    ('address = "127.0.0.1"', "dyno.address", "out of range"),
    ('interface = "virtual"', "can.interface", "not a python-can interface"),
    ('channel = "eol"', "can.channel", "expected str"),
    ('key_file = "ecu.key"', "key_file", "no such file"),
    ('db = "records.sqlite"', "dbx", "unknown key"),
])
def test_bad_keys_are_named(station_dir: Path, edit: str, key: str, words: str) -> None:
    replacement = {
        "station_id": "", "dyno.address": "", "can.interface": 'interface = "kvasr"', "can.channel": "channel = 5",
        "key_file": 'key_file = "missing.key"', "dbx": 'dbx = "records.sqlite"',
    }[key]
    if key == "dyno.address" and words == "out of range":
        replacement = 'address = "127.0.0.1:70000"'
    text = GOOD.replace(edit, replacement)
    (station_dir / "station.toml").write_text(text)
    err = _refused(station_dir / "station.toml")
    assert err.field == key and words in err.reason
    assert err.file == str(station_dir / "station.toml")


def test_bad_environment_value_names_the_variable(station_dir: Path) -> None:
    err = _refused(station_dir / "station.toml", {"EOL_CAL_RATE_HZ": "fast"})
    assert (err.file, err.field) == ("$EOL_CAL_RATE_HZ", "rate_hz")


def test_bool_is_not_a_rate(station_dir: Path) -> None:
    # a key after a table header belongs to the table: put it at the top
    (station_dir / "station.toml").write_text("rate_hz = true\n" + GOOD)
    err = _refused(station_dir / "station.toml")
    assert err.field == "rate_hz" and "expected int" in err.reason


@pytest.mark.parametrize("key, value, words", [
    ("variant", "NOPE", "not in the file"),
    ("profile", "no-such-profile", "no such profile"),
    ("bench", "no-such-bench", ""),
])
def test_check_station_names_the_key(station_dir: Path, key: str, value: str, words: str) -> None:
    err = _refused(station_dir / "station.toml", {env_name(key): value}, check=True)
    assert err.field == key and err.file == f"${env_name(key)}" and words in err.reason


def test_non_utf8_and_not_toml(station_dir: Path) -> None:
    p = station_dir / "station.toml"
    p.write_bytes(b"station_id = \"\xff\"\n")
    assert "UTF-8" in _refused(p).reason
    p.write_text("station_id = \n")
    assert "TOML" in _refused(p).reason


def test_dyno_register_map_key_names_a_shipped_map_or_a_file_beside_the_settings(station_dir: Path) -> None:
    from eol_cal.station.settings import register_map_of

    s = load_settings(station_dir / "station.toml", {})
    assert register_map_of(s).name == "eol-cal reference dyno"  # the default
    s = load_settings(station_dir / "station.toml", {env_name("dyno.register_map"): "vendor-b"})
    assert register_map_of(s).word_order == "little"
    text = (Path(__file__).resolve().parents[1] / "eol_cal" / "dyno" / "maps" / "vendor-b.toml").read_text()
    (station_dir / "maps").mkdir()
    (station_dir / "maps" / "rig3.toml").write_text(
        text.replace("scale = 0.1                 # 0.1 rpm", "scale = 0                   # 0.1 rpm"))
    (station_dir / "station.toml").write_text(
        GOOD.replace('address = "127.0.0.1"', 'address = "127.0.0.1"\nregister_map = "maps/rig3.toml"'))
    err = _refused(station_dir / "station.toml", check=True)
    assert err.field == "dyno.register_map" and "rig3.toml" in str(err) and "registers.speed.scale" in str(err)


def test_the_estimator_options_come_from_the_settings_or_the_variant(station_dir: Path) -> None:
    from eol_cal.firmware.options import parse_options
    from eol_cal.station.configure import station_config

    s = load_settings(station_dir / "station.toml", {})
    cfg = station_config(s)
    assert cfg.estimator is None and cfg.estimator_options == cfg.limits.estimator_options  # the variant's
    s = load_settings(station_dir / "station.toml", {env_name("estimator"): "paper"})
    check_station(s)
    cfg = station_config(s)
    assert cfg.estimator == "paper" and cfg.estimator_options == parse_options("paper") == 0
    err = _refused(station_dir / "station.toml", {env_name("estimator"): "fastest"}, check=True)
    assert err.field == "estimator" and err.file == f"${env_name('estimator')}"
