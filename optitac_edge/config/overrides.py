"""The environment's ``OPTITAC_<SECTION>_<KEY>`` and the command line's ``section.key`` overrides."""

from __future__ import annotations

from optitac_edge.config.sections import _LISTS, _SECTIONS
from optitac_edge.errors import ConfigError
from optitac_edge.io.publishers import PUBLISHERS

#: Prefix of the environment variables that override file values.
ENV_PREFIX = "OPTITAC_"


#: Variables with the prefix that are not config overrides (tools/install.sh's, the tests' soak length).
NOT_CONFIG_VARS = frozenset({"OPTITAC_PYTHON", "OPTITAC_SOAK_MINUTES", "OPTITAC_WHEEL_CACHE"})
#: The program's own switches (``OPTITAC_EDGE_KERNEL=numpy``: core/compiled.py), not config overrides: no
#: config section is named ``edge``.
NOT_CONFIG_PREFIX = "OPTITAC_EDGE_"


def _env_key(var: str) -> tuple[str, str] | None:
    """``OPTITAC_LINK_SERIAL_URL`` -> ("link", "serial_url"); None for :data:`NOT_CONFIG_VARS`.

    Raises
    ------
    ConfigError
        For a section that does not exist (``OPTITAC_LNK_TRANSPORT`` was ignored without a word).
    """
    if var in NOT_CONFIG_VARS or var.startswith(NOT_CONFIG_PREFIX):
        return None
    rest = var[len(ENV_PREFIX):].lower()
    section, _, key = rest.partition("_")
    if section == "publish":
        name, _, key = key.partition("_")
        if name not in PUBLISHERS or not key:
            raise ConfigError(f"environment {var}: publishers are set as OPTITAC_PUBLISH_<NAME>_<KEY> "
                              f"(NAME: {', '.join(PUBLISHERS)})")
        return section, f"{name}.{key}"
    if section in _LISTS:
        raise ConfigError(f"environment {var}: cameras and sensors are set in the board file "
                          "(or on the command line as cameras.NAME.KEY)")
    if section not in _SECTIONS:
        raise ConfigError(f"environment {var}: no section {section!r} (sections: {', '.join(sorted(_SECTIONS))})")
    if section == "camera" and key.startswith("options_"):
        return section, "options." + key[len("options_"):]
    return section, key


def _split_override(key: str) -> tuple[str, str]:
    section, dot, rest = key.partition(".")
    if not dot or not rest:
        raise ConfigError(f"command line: {key}: overrides are written section.key=value")
    return section, rest
