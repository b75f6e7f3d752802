"""The service's glue: board configs map onto the camera backends' real constructor arguments."""

from __future__ import annotations

import importlib
import inspect

import pytest

from optitac_edge.board_config import available_boards, load_board_config
from optitac_edge.cameras import BACKENDS
from optitac_edge.service import camera_kwargs


@pytest.mark.parametrize("board", sorted(available_boards()))
def test_every_packaged_board_gives_arguments_its_camera_backend_accepts(board):
    config = load_board_config(board, env={})
    module_name, class_name = BACKENDS[config.camera.backend].split(":")
    cls = getattr(importlib.import_module(module_name), class_name)
    inspect.signature(cls).bind(**camera_kwargs(config))  # raises TypeError on an unknown argument


def test_cli_and_environment_override_the_file():
    config = load_board_config("sim", env={"OPTITAC_CAMERA_FPS": "90"}, overrides={"link.rate_divider": 3})
    assert config.camera.fps == 90 and config.link.rate_divider == 3
    config = load_board_config("sim", env={"OPTITAC_CAMERA_FPS": "90"}, overrides={"camera.fps": 30})
    assert config.camera.fps == 30
