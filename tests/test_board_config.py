"""Board configs: the packaged files load, precedence, and one-line errors naming file and key."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from optitac_edge.config import (
    BoardConfig,
    available_boards,
    describe_schema,
    load_board_config,
    resolve_board_config,
)
from optitac_edge.errors import ConfigError
from optitac_edge.service.wiring import config_warnings

REPO = Path(__file__).resolve().parents[1]
PACKAGED = ["sim", "rpi5-gs", "rpi4-cm3", "jetson-orin-nano-usb", "jetson-csi"]


@pytest.mark.parametrize("name", PACKAGED)
def test_packaged_boards_load(name):
    cfg = load_board_config(name, env={})
    assert isinstance(cfg, BoardConfig)
    assert Path(cfg.source).name == f"{name}.toml"
    assert config_warnings(cfg) == []
    assert set(cfg.as_dict()) == {"sensor", "camera", "calibration", "link", "led", "status", "watchdog", "rig",
                                 "network", "publish"}


def test_available_boards_and_repo_dir():
    assert set(PACKAGED) <= set(available_boards())
    assert resolve_board_config("sim") == REPO / "board_configs" / "sim.toml"


def test_sim_is_the_default_and_needs_no_hardware():
    cfg = load_board_config(env={})
    assert cfg.camera.backend == "sim"
    assert cfg.link.transport == "none"
    assert not cfg.led.enabled
    assert cfg.calibration.bundle_path is None


def test_packaged_details():
    gs = load_board_config("rpi5-gs", env={})
    assert gs.camera.backend == "picamera2" and gs.camera.pixel_format == "yuv420"
    assert gs.led.address == 0x40 and gs.led.channels == (0, 1, 2, 3)
    assert gs.link.serial_url == "/dev/optitac-mcu"
    assert gs.calibration.bundle_path == Path("/var/lib/optitac-edge/calibration.npz")
    usb = load_board_config("jetson-orin-nano-usb", env={})
    assert usb.camera.device.startswith("/dev/v4l/by-id/")
    assert usb.link.transport == "can" and usb.link.can_channel == "can0"
    assert dict(usb.camera.options) == {"fourcc": "YUYV"}
    csi = load_board_config("jetson-csi", env={})
    assert "nvarguscamerasrc" in csi.camera.pipeline and csi.camera.device == ""


def test_empty_file_gives_defaults(tmp_path):
    path = tmp_path / "empty.toml"
    path.write_text("")
    cfg = load_board_config(path, env={})
    assert cfg == BoardConfig(source=cfg.source)
    assert cfg.camera.fps == 60.0 and cfg.status.period_s == 1.0


def test_state_directory_sets_default_bundle(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text("")
    cfg = load_board_config(path, env={"STATE_DIRECTORY": "/var/lib/x:/var/lib/y"})
    assert cfg.calibration.bundle == "/var/lib/x/calibration.npz"


def test_relative_paths_resolve_against_the_file(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text('[calibration]\nbundle = "cal/bundle.npz"\nlayout = "layout.csv"\n')
    cfg = load_board_config(path, env={})
    assert cfg.calibration.bundle_path == tmp_path / "cal" / "bundle.npz"
    assert cfg.calibration.layout_path == tmp_path / "layout.csv"


def test_precedence_file_env_command_line(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text('[camera]\nfps = 30\nwidth = 320\n[link]\ntransport = "serial"\nserial_url = "/dev/ttyACM0"\n')
    env = {"OPTITAC_CAMERA_FPS": "45", "OPTITAC_LINK_SERIAL_URL": "loop://", "OPTITAC_LED_ADDRESS": "0x41",
           "OPTITAC_LED_CHANNELS": "0, 1,2", "OPTITAC_LED_ENABLED": "yes", "OPTITAC_CAMERA_OPTIONS_HDR": "true",
           "PATH": "/usr/bin"}
    cfg = load_board_config(path, env=env, overrides={"camera.fps": 90, "sensor.id": "7"})
    assert cfg.camera.fps == 90.0  # command line beats environment
    assert cfg.camera.width == 320  # file
    assert cfg.link.serial_url == "loop://"  # environment beats file
    assert cfg.led.address == 0x41 and cfg.led.channels == (0, 1, 2) and cfg.led.enabled
    assert cfg.sensor.id == 7
    assert cfg.camera.options["hdr"] is True
    assert cfg.origins["camera.fps"] == "command line"
    assert cfg.origins["link.serial_url"] == "environment OPTITAC_LINK_SERIAL_URL"
    assert cfg.origins["camera.width"].endswith("b.toml")


def test_configs_are_frozen():
    cfg = load_board_config("sim", env={})
    with pytest.raises(AttributeError):
        cfg.camera.fps = 1  # type: ignore[misc]
    with pytest.raises(TypeError):
        cfg.camera.options["x"] = 1  # type: ignore[index]


def test_schema_text_lists_every_section():
    text = describe_schema()
    for section in ("[sensor]", "[camera]", "[calibration]", "[link]", "[led]", "[status]", "[watchdog]"):
        assert section in text


# ---------------------------------------------------------------- malformed corpus: (toml, key, words)
BAD_FILES = [
    ('[camera]\nfps = "fast"\n', "camera.fps", "must be a number in 1..1000, got 'fast'"),
    ("[camera]\nfps = 0\n", "camera.fps", "must be a number in 1..1000"),
    ("[camera]\nfps = 1e9\n", "camera.fps", "1..1000"),
    ("[camera]\nfps = nan\n", "camera.fps", "must be a number"),
    ("[camera]\nfps = true\n", "camera.fps", "boolean"),
    ("[camera]\nwidth = 640.5\n", "camera.width", "must be an integer"),
    ("[camera]\nwidth = 8\n", "camera.width", "16..8192"),
    ('[camera]\nbackend = "webcam"\n', "camera.backend", "must be one of"),
    ('[camera]\npixel_format = "bgr"\n', "camera.pixel_format", "'gray', 'rgb', 'yuv420'"),
    ("[camera]\nexposure_us = -1\n", "camera.exposure_us", "0..10000000"),
    ("[camera]\ntimeout_s = 0\n", "camera.timeout_s", "must be a number in 0.001..60, got 0"),
    ("[camera]\nframerate = 30\n", "camera.framerate", "unknown key"),
    ("[camera]\nFPS = 30\n", "camera.FPS", "did you mean fps"),
    ("[camera.options]\nnested = { a = 1 }\n", "camera.options.nested", "must be a scalar"),
    ("[camera.options]\nlist = [1, 2]\n", "camera.options.list", "must be a scalar"),
    ("[camera]\noptions = 3\n", "camera.options", "must be a table"),
    ('[camera]\nbackend = "v4l2"\n', "camera.device", "exactly one of camera.device and camera.pipeline"),
    ('[camera]\nbackend = "v4l2"\ndevice = "/dev/video0"\npipeline = "x ! appsink"\n', "camera.pipeline",
     "exactly one of"),
    ('[camera]\nbackend = "v4l2"\npipeline = "videotestsrc ! fakesink"\n', "camera.pipeline", "appsink"),
    ('[camera]\nbackend = "recording"\n', "camera.recording", "needs camera.recording"),
    ('[camera]\npipeline = "a ! appsink"\n', "camera.pipeline", "only the v4l2 backend"),
    ('[camera]\npixel_format = "yuv420"\nwidth = 641\n', "camera.pixel_format", "even width"),
    ("[sensor]\nid = 256\n", "sensor.id", "must be an integer in 0..255, got 256"),
    ('[sensor]\nid = "1"\n', "sensor.id", "got '1'"),
    ('[sensor]\nname = "left gripper"\n', "sensor.name", "must match"),
    ('[sensor]\nname = ""\n', "sensor.name", "must not be empty"),
    ("[calibration]\nbundle = 3\n", "calibration.bundle", "must be a string"),
    ('[calibration]\nif_missing = "ignore"\n', "calibration.if_missing", "'calibrate', 'fail'"),
    ('[calibration]\nmirror = "yes"\n', "calibration.mirror", "must be true or false"),
    ("[calibration]\nrotation_deg = 400\n", "calibration.rotation_deg", "-360..360"),
    ('[link]\ntransport = "usb"\n', "link.transport", "'serial', 'can', 'none'"),
    ('[link]\ntransport = "serial"\n', "link.serial_url", "required when link.transport is 'serial'"),
    ('[link]\ntransport = "can"\ncan_channel = ""\n', "link.can_channel", "required"),
    ("[link]\nbaudrate = 300\n", "link.baudrate", "1200..12000000"),
    ("[link]\ncan_bitrate = 2000000\n", "link.can_bitrate", "10000..1000000"),
    ("[link]\nrate_divider = 0\n", "link.rate_divider", "1..1000"),
    ('[link]\ncan_interface = "Socket CAN"\n', "link.can_interface", "must match"),
    ("[led]\nbrightness = 1.5\n", "led.brightness", "must be a number in 0..1, got 1.5"),
    ("[led]\naddress = 0x80\n", "led.address", "7-bit I2C address"),
    ("[led]\nchannels = [0, 16]\n", "led.channels", "0..15"),
    ("[led]\nchannels = [1, 1]\n", "led.channels", "unique"),
    ("[led]\nchannels = []\n", "led.channels", "non-empty"),
    ('[led]\ndriver = "tlc5947"\n', "led.driver", "'pca9685'"),
    ("[led]\npwm_frequency_hz = 5000\n", "led.pwm_frequency_hz", "24..1526"),
    ("[led]\nmax_peak = 300\n", "led.max_peak", "1..255"),
    ("[status]\nperiod_s = 0\n", "status.period_s", "0.05..3600"),
    ("[watchdog]\nmax_frame_gap_s = -1\n", "watchdog.max_frame_gap_s", "0.1..600"),
    ("[camra]\nfps = 30\n", "camra", "unknown section"),
    ("[cameras]\nfps = 30\n", "cameras.fps", "must be a table [cameras.fps]"),
    ("fps = 30\n", "fps", "unknown key"),
    ("camera = 3\n", "camera", "must be a table"),
    ("config_version = 2\n", "config_version", "must be 1"),
    ("description = 5\n", "description", "must be a string"),
]


@pytest.mark.parametrize(("text", "key", "words"), BAD_FILES, ids=[k for _, k, _ in BAD_FILES])
def test_malformed_file_gives_one_line_naming_file_and_key(tmp_path, text, key, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_board_config(path, env={})
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: {key}: "), message
    assert words in message, message


def test_unparseable_toml(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("[camera\nfps = 30\n")
    with pytest.raises(ConfigError, match=r"broken\.toml: not valid TOML") as info:
        load_board_config(path, env={})
    assert "\n" not in str(info.value)


def test_binary_file(tmp_path):
    path = tmp_path / "bin.toml"
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match=r"bin\.toml: "):
        load_board_config(path, env={})


@pytest.mark.parametrize("name", ["nope", "missing/board.toml", "missing.toml"])
def test_missing_file_or_board(name):
    with pytest.raises(ConfigError) as info:
        load_board_config(name, env={})
    message = str(info.value)
    assert "\n" not in message and message.startswith(name)
    assert ("no such board" if name == "nope" else "board config not found") in message


def test_unknown_board_lists_known():
    with pytest.raises(ConfigError, match="known: .*sim"):
        load_board_config("nope", env={})


BAD_ENV = [
    ("OPTITAC_CAMERA_FPS", "fast", "camera.fps", "must be a number in 1..1000 (ASCII digits), got 'fast'"),
    # Python's int() and float() take these: 30_0 as 300, an Arabic-Indic three as 3
    ("OPTITAC_CAMERA_FPS", "30_0", "camera.fps", "got '30_0'"),
    ("OPTITAC_CAMERA_WIDTH", "\u0663\u0662\u0660", "camera.width", "ASCII digits"),
    ("OPTITAC_LED_CHANNELS", "0,1_0", "led.channels", "channel numbers"),
    ("OPTITAC_CAMERA_FRAMERATE", "30", "camera.framerate", "unknown key"),
    ("OPTITAC_LED_ADDRESS", "sixty-four", "led.address", "7-bit"),
    ("OPTITAC_LED_CHANNELS", "0,x", "led.channels", "channel numbers"),
    ("OPTITAC_LED_ENABLED", "maybe", "led.enabled", "true or false"),
    ("OPTITAC_SENSOR_ID", "-1", "sensor.id", "0..255"),
    ("OPTITAC_LINK_TRANSPORT", "serial", "link.serial_url", "required"),
    # issue 38, item 20: a period no integer holds was an OverflowError at start
    ("OPTITAC_NETWORK_PICTURE_HZ", "1e-300", "network.picture_hz", "0 (none) or a rate in 0.001..120"),
    ("OPTITAC_NETWORK_SIGNAL_HZ", "1e-9", "network.signal_hz", "0 (none) or a rate in 0.001..1000"),
]


@pytest.mark.parametrize(("var", "value", "key", "words"), BAD_ENV, ids=[f"{v}={x}" for v, x, *_ in BAD_ENV])
def test_bad_environment_names_the_variable(var, value, key, words):
    with pytest.raises(ConfigError) as info:
        load_board_config("sim", env={var: value})
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"environment {var}: {key}: "), message
    assert words in message


@pytest.mark.parametrize(("overrides", "key", "words"), [
    ({"camera.fps": "fast"}, "camera.fps", "got 'fast'"),
    ({"camera.fps": None}, "camera.fps", "must be a number"),
    ({"led.brightness": 2}, "led.brightness", "0..1"),
    ({"nosuch.key": 1}, "nosuch", "unknown section"),
    ({"fps": 1}, "fps", "section.key=value"),
])
def test_bad_command_line_override(overrides, key, words):
    with pytest.raises(ConfigError) as info:
        load_board_config("sim", env={}, overrides=overrides)
    message = str(info.value)
    assert message.startswith(f"command line: {key}: ") and words in message, message


def test_warnings_for_led_flicker(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text("[camera]\nexposure_us = 1500\nfps = 60\n[led]\nenabled = true\npwm_frequency_hz = 1000\n")
    warnings = config_warnings(load_board_config(path, env={}))
    assert len(warnings) == 1 and "flicker" in warnings[0]
    path.write_text("[camera]\nexposure_us = 30000\nfps = 60\n")
    assert "longer than a frame" in config_warnings(load_board_config(path, env={}))[0]


def test_a_misspelt_section_in_the_environment_is_refused_not_ignored():
    """OPTITAC_LNK_TRANSPORT=serial ran the service with no link, without a word."""
    with pytest.raises(ConfigError, match=r"environment OPTITAC_LNK_TRANSPORT: no section 'lnk' \(sections: "):
        load_board_config("sim", env={"OPTITAC_LNK_TRANSPORT": "serial"})
    load_board_config("sim", env={"OPTITAC_PYTHON": "/usr/bin/python3"})  # tools/install.sh's, not config


def test_a_deeply_nested_board_file_is_one_line(tmp_path):
    path = tmp_path / "deep.toml"
    path.write_text("[camera]\nwidth = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_board_config(path, env={})


@pytest.mark.parametrize("text", ["30_0", "\u0663", "1e3", ""])
def test_command_line_numbers_are_ascii_digits(text, capsys):
    from optitac_edge.cli import main

    with pytest.raises(SystemExit) as ex:
        main(["sim", "x", "--scenario", "rest", "--frames", text])
    assert ex.value.code == 2 and "is not an integer" in capsys.readouterr().err


def test_the_camera_backends_a_config_may_name_are_the_registrys(tmp_path, monkeypatch):
    """One list of camera names: the registry (io/cameras CAMERAS); a backend added there is valid in a board
    config, and the refusal names exactly the registry's names."""
    from optitac_edge.io import cameras

    path = tmp_path / "board.toml"
    path.write_text('[camera]\nbackend = "webcam"\n')
    with pytest.raises(ConfigError) as info:
        load_board_config(path, env={})
    assert "must be one of " + ", ".join(repr(n) for n in sorted(cameras.CAMERAS)) in str(info.value)
    monkeypatch.setitem(cameras.CAMERAS, "webcam", "my_cameras:Webcam")
    assert load_board_config(path, env={}).camera.backend == "webcam"


# -- publishers: [publish.NAME] and [network] ------------------------------------------------------------


def test_each_publisher_is_a_section_named_after_its_registry_entry(tmp_path):
    from optitac_edge.io.device import BoardView
    from optitac_edge.io.publishers.mcap import McapPublish, McapPublisher
    from optitac_edge.io.publishers.zenoh import ZenohPublish

    board = tmp_path / "b.toml"
    board.write_text('[network]\nnamespace = "/robot1"\n[publish.mcap]\npath = "run.mcap"\nmax_mb = 50\n'
                     '[publish.zenoh]\nmode = "client"\nconnect = ["tcp/192.168.1.10:7447"]\n')
    cfg = load_board_config(board, env={})
    assert list(cfg.publish) == ["mcap", "zenoh"] and cfg.network.namespace == "/robot1"
    assert cfg.publish["mcap"] == McapPublish(path=str(tmp_path / "run.mcap"), max_mb=50.0)
    assert cfg.publish["zenoh"] == ZenohPublish(mode="client", connect=("tcp/192.168.1.10:7447",))
    assert cfg.view("publish.mcap") == BoardView(source=str(board), key="publish.mcap", namespace="/robot1")
    with McapPublisher.from_config(cfg.publish["mcap"], cfg.view("publish.mcap")) as recorder:
        assert (recorder.max_bytes, recorder.max_ns, recorder.namespace) == (50_000_000, 0, "/robot1")


def test_an_old_publish_section_loads_as_the_new_form_with_a_one_line_hint(tmp_path, caplog):
    old, new = tmp_path / "old.toml", tmp_path / "new.toml"
    old.write_text('[publish]\nbackend = "zenoh"\nconnect = ["tcp/10.0.0.2:7447"]\nnamespace = "/r"\nqueue = 64\n'
                   'foxglove = "0.0.0.0:8765"\n[mcap]\npath = "x.mcap"\nkeep_mb = 10\n')
    new.write_text('[network]\nnamespace = "/r"\nqueue = 64\n[publish.zenoh]\nconnect = ["tcp/10.0.0.2:7447"]\n'
                   '[publish.foxglove]\nbind = "0.0.0.0:8765"\n[publish.mcap]\npath = "x.mcap"\nkeep_mb = 10\n')
    with caplog.at_level("WARNING"):
        a = load_board_config(old, env={})
    b = load_board_config(new, env={})
    assert a.publish == b.publish and a.network == b.network
    (hint,) = [r.getMessage() for r in caplog.records]
    assert "old form" in hint and "[publish.zenoh]" in hint and "network.namespace" in hint and "\n" not in hint
    off = tmp_path / "off.toml"
    off.write_text('[publish]\nbackend = "none"\nsignal_hz = 5\n')
    assert load_board_config(off, env={}).publish == {} and load_board_config(off, env={}).network.signal_hz == 5


@pytest.mark.parametrize(("text", "env", "message"), [
    ('[publish.ros]\nmode = "client"\n', {}, "publish.ros: no such publisher (known: zenoh, foxglove, mcap, virtual)"),
    ('[publish.zenoh]\nmod = "client"\n', {}, "publish.zenoh.mod: unknown key"),
    ('[publish.mcap]\nmax_mb = 5\n', {}, "publish.mcap.path: required"),
    ('[publish.zenoh]\nmode = "peer"\n', {"OPTITAC_PUBLISH_BACKEND": "zenoh"},
     "environment OPTITAC_PUBLISH_BACKEND: publishers are set as OPTITAC_PUBLISH_<NAME>_<KEY>"),
])
def test_bad_publishers_are_one_line_naming_the_key(tmp_path, text, env, message):
    board = tmp_path / "b.toml"
    board.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_board_config(board, env=env)


def test_the_environment_and_command_line_set_a_publisher_by_its_name(tmp_path):
    board = tmp_path / "b.toml"
    board.write_text('[publish.zenoh]\nmode = "client"\n')
    cfg = load_board_config(board, env={"OPTITAC_PUBLISH_ZENOH_DOMAIN_ID": "7"},
                            overrides={"publish.mcap.path": "r.mcap"})
    assert cfg.publish["zenoh"].domain_id == 7 and list(cfg.publish) == ["zenoh", "mcap"]
    assert load_board_config(board, env={}, overrides={"publish.zenoh": False}).publish == {}


@pytest.mark.parametrize(("text", "message"), [
    ('[publish]\nbackend = "none"\ndomain_id = 999\n', "publish.zenoh.domain_id: must be an integer in 0..232"),
    ('[publish]\nbackend = "virtual"\nmod = "client"\n', "publish.zenoh.mod: unknown key"),
    ('[mcap]\nmax_mb = -1\n', "publish.mcap.max_mb: must be a number in 0..1e+07"),
    ('[mcap]\npat = "x.mcap"\n', "publish.mcap.pat: unknown key"),
])
def test_an_old_publish_section_is_checked_also_where_it_publishes_nothing(tmp_path, text, message):
    """The old form checked [publish] and [mcap] keys whatever the backend or path (a bad value was one line,
    not silently dropped); read as the new tables it still does."""
    board = tmp_path / "b.toml"
    board.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_board_config(board, env={})


def test_a_board_loads_when_the_working_directory_was_removed(tmp_path) -> None:
    """A long run whose working directory is deleted under it (a checkout replaced, a temporary directory
    cleaned) still reads a board config: the file is named as given, not a FileNotFoundError traceback."""
    import subprocess
    import sys

    gone = tmp_path / "gone"
    gone.mkdir()
    board = tmp_path / "b.toml"
    board.write_text('[camera]\nbackend = "sim"\n')
    code = ("import os, sys; os.chdir(sys.argv[1]); os.rmdir(sys.argv[1])\n"
            "from optitac_edge.config import load_board_config\n"
            "print(load_board_config(sys.argv[2], env={}).source)")
    out = subprocess.run([sys.executable, "-c", code, str(gone), str(board)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == str(board)
