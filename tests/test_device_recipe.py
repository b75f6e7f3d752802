"""One recipe for every kind of device: a new publisher or rig is one module and one registry line.

Each test writes the one module (a publisher or a rig as a user would, in its own file) and adds the one
registry line (``REGISTRY["name"] = "module:Class"``); nothing else of the package changes, and the board
config, the environment, the command line, the service and ``collect``'s rig opener all take it.
"""

from __future__ import annotations

import textwrap

import pytest

from optitac_edge.cli import main
from optitac_edge.config import load_board_config
from optitac_edge.errors import ConfigError, RigError
from optitac_edge.io.publishers import PUBLISHERS
from optitac_edge.io.rigs import RIGS

PUBLISHER_MODULE = '''
"""A publisher of a user's own: keeps what it is given, under a port and a log path of its own section."""

from dataclasses import dataclass

from optitac_edge.fields import integer, path_text, setting
from optitac_edge.io.publishers.base import Publisher

TAKEN = []


@dataclass(frozen=True)
class UdpPublish:
    """``[publish.udp]``: a UDP sink (this test's)."""

    port: int = setting(integer(1, 65535), 7400, "UDP port")
    log: str = setting(path_text, "", "where it logs", required=True)


class UdpPublisher(Publisher):
    Section = UdpPublish

    @classmethod
    def from_config(cls, section, board):
        return cls(section.port, section.log, board.namespace)

    def __init__(self, port, log, namespace):
        super().__init__()
        self.port, self.log, self.namespace = port, log, namespace
        self.topics = []
        TAKEN.append(self)

    def advertise(self, topic, type_name):
        self.topics.append(topic)
        return len(self.topics) - 1

    def publish(self, handle, payload, source_ns):
        self.messages = getattr(self, "messages", 0) + 1
'''

RIG_MODULE = '''
"""A rig of a user's own (``table://NAME``): moves at once, reports where it is."""

from optitac_edge.io.rigs.base import Rig, RigStatus, url_rest


class TableRig(Rig):
    @classmethod
    def from_url(cls, url, config):
        return cls(url_rest(url, "table"), config.limits())

    def __init__(self, name, limits):
        super().__init__(limits)
        self.name = name
        self.xyz = (0.0, 0.0, limits.safe_z_mm)

    def _move(self, xyz, feed_mm_s):
        self.xyz = xyz

    def _status(self):
        return RigStatus("idle", self.xyz)

    def _stop(self):
        pass
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """Write ``NAME.py`` (the one module) where Python finds it."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def write(name: str, source: str) -> None:
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(source))

    return write


def test_a_new_publisher_is_one_module_and_one_registry_line(tmp_path, monkeypatch, user_module):
    user_module("udp_publisher", PUBLISHER_MODULE)
    monkeypatch.setitem(PUBLISHERS, "udp", "udp_publisher:UdpPublisher")  # the one registry line
    import udp_publisher

    board = tmp_path / "b.toml"
    board.write_text('[network]\nnamespace = "/r1"\n[publish.udp]\nport = 9000\nlog = "udp.log"\n')
    config = load_board_config(board, env={"OPTITAC_PUBLISH_UDP_PORT": "9001"}, overrides={})
    section = config.publish["udp"]
    assert (section.port, section.log) == (9001, str(tmp_path / "udp.log"))  # env wins; a path key is resolved

    # its keys are checked as every section's: range, unknown key, required
    board.write_text("[publish.udp]\nport = 0\nlog = 'x'\n")
    with pytest.raises(ConfigError, match=r"publish\.udp\.port: must be an integer in 1\.\.65535"):
        load_board_config(board, env={})
    board.write_text("[publish.udp]\nprot = 1\n")
    with pytest.raises(ConfigError, match=r"publish\.udp\.prot: unknown key \(known: port, log\)"):
        load_board_config(board, env={})
    board.write_text("[publish.udp]\nport = 9000\n")
    with pytest.raises(ConfigError, match=r"publish\.udp\.log: required"):
        load_board_config(board, env={})

    # the service opens it and publishes every sensor's topics on it
    board.write_text('[network]\nnamespace = "/r1"\n[publish.udp]\nlog = "udp.log"\n'
                     f'[calibration]\nbundle = "{tmp_path / "cal.npz"}"\n')
    assert main(["run", "--board", str(board), "--frames", "40", "--quiet"]) == 0
    (publisher,) = udp_publisher.TAKEN
    assert publisher.namespace == "/r1" and publisher.port == 7400 and publisher.closed
    assert "/r1/optitac/optitac/contacts" in publisher.topics and publisher.messages >= 40


def test_a_new_rig_is_one_module_and_one_registry_line(tmp_path, monkeypatch, user_module):
    from optitac_edge.bringup.rigs import open_rig

    user_module("table_rig", RIG_MODULE)
    monkeypatch.setitem(RIGS, "table", "table_rig:TableRig")  # the one registry line

    board = tmp_path / "b.toml"
    board.write_text("[rig]\nurl = 'table://bench1'\nx_min = 0\nx_max = 10\ny_min = 0\ny_max = 10\n"
                     "z_min = -2\nz_max = 5\n")
    rig, camera = open_rig(load_board_config(board, env={}))
    with rig:
        assert type(rig).__name__ == "TableRig" and rig.name == "bench1" and camera is None
        rig.move_to((5.0, 5.0, 0.0))
        assert rig.status().xyz_mm == (5.0, 5.0, 0.0)
        with pytest.raises(RigError, match="outside"):  # the base class keeps every rig inside its limits
            rig.move_to((50.0, 5.0, 0.0))

    with pytest.raises(RigError, match="set the rig's travel limits"):  # a real rig needs its limits
        open_rig(load_board_config("sim", env={}), "table://bench1")
    with pytest.raises(RigError, match=r"unknown rig URL 'table:bench1' \(a table rig is table://\.\.\.\)"):
        open_rig(load_board_config(board, env={}), "table:bench1")
    monkeypatch.delitem(RIGS, "table")
    with pytest.raises(RigError, match=r"unknown rig URL 'table://bench1' \(known: gcode://\.\.\., sim://\.\.\., "
                                       r"ur://\.\.\.\)"):
        open_rig(load_board_config(board, env={}))
