"""Backends of one kind of device, by name, each a ``"module:Class"`` imported when first used.

As python-can's ``BACKENDS``: a registry line names the class and the pip extra of the optional library it
needs; :meth:`Registry.open` is the one way from a config section to a device::

    PUBLISHERS = Registry("publisher", PublishError, {
        "zenoh": Backend("optitac_edge.io.publishers.zenoh:ZenohPublisher", extra="zenoh"),
    })
    publisher = PUBLISHERS.open("zenoh", section, board)   # ZenohPublisher.from_config(section, board)

Another package adds its own through an entry point group (``[project.entry-points."GROUP"]``,
``name = "module:Class"``): the simulator adds its camera and its rig this way from the layer above.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping, MutableMapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from optitac_edge.errors import OptiTacError, missing_extra

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.io.device import BoardView


@dataclass(frozen=True)
class Backend:
    """One registry line: the class, and the pip extra that installs what it imports when used."""

    #: ``"package.module:Class"``.
    target: str
    #: ``pip install 'optitac-edge[EXTRA]'`` installs its optional library ('' = it needs none).
    extra: str = ""


class Configurable(Protocol):
    """A device class opened from its config section (its own dataclass) and the board it is on."""

    @classmethod
    def from_config(cls, section: Any, board: BoardView) -> Self: ...


D = TypeVar("D")
C = TypeVar("C", bound=Configurable)


def _entry_points(group: str) -> dict[str, Backend]:
    from importlib.metadata import entry_points

    return {ep.name: Backend(ep.value) for ep in entry_points(group=group)}


class Registry(MutableMapping[str, Backend], Generic[D]):
    """Backends of one ``kind`` by name; failures raise ``error`` (one line naming the name and the known ones).

    Parameters
    ----------
    kind : str
        How messages name the kind (``"camera backend"``, ``"publisher"``).
    error : type
        The :class:`~optitac_edge.errors.OptiTacError` an unknown name raises.
    backends : Mapping[str, Backend | str]
        Name -> registry line (a bare ``"module:Class"`` needs no extra).
    group : str
        An entry point group other packages add backends through ('' = none).
    """

    def __init__(self, kind: str, error: type[OptiTacError], backends: Mapping[str, Backend | str],
                 group: str = "") -> None:
        self.kind = kind
        self.error = error
        self.group = group
        lines = {name: b if isinstance(b, Backend) else Backend(b) for name, b in backends.items()}
        self._backends = {**lines, **(_entry_points(group) if group else {})}

    def __getitem__(self, name: str) -> Backend:
        return self._backends[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._backends)

    def __len__(self) -> int:
        return len(self._backends)

    def __setitem__(self, name: str, backend: Backend | str) -> None:
        """Register one more backend (what a registry line does; a test's own, or a plugin's)."""
        self._backends[name] = backend if isinstance(backend, Backend) else Backend(backend)

    def __delitem__(self, name: str) -> None:
        del self._backends[name]

    def _unknown(self, name: str) -> OptiTacError:
        return self.error(f"unknown {self.kind} {name!r} (known: {', '.join(sorted(self._backends))})")

    def load(self, name: str) -> type[D]:
        """The class registered as ``name``, its module imported on first use.

        Raises
        ------
        OptiTacError
            ``error`` for an unknown name; :class:`~optitac_edge.errors.MissingExtraError` (naming the
            extra) when the module needs an optional library that is not installed.
        """
        try:
            backend = self._backends[name]
        except KeyError:
            raise self._unknown(name) from None
        module_name, class_name = backend.target.split(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            raise self._missing(exc, name, backend) from None
        cls: type[D] = getattr(module, class_name)
        return cls

    def open(self: Registry[C], name: str, section: object, board: BoardView) -> C:
        """The device ``name`` opened from its config ``section`` and its ``board``
        (:class:`~optitac_edge.io.device.BoardView`): ``Class.from_config(section, board)``.

        Raises
        ------
        OptiTacError
            As :meth:`load`, and whatever the backend raises when it cannot open (a missing optional
            library imported only when opened is reported as by :meth:`load`).
        """
        cls = self.load(name)
        with self.importing(name):
            return cls.from_config(section, board)

    def make(self, name: str, **kwargs: Any) -> D:
        """The device ``name`` made with its constructor's ``kwargs`` (no board config: tests, dev tools);
        failures reported as by :meth:`open`."""
        cls = self.load(name)
        with self.importing(name):
            return cls(**kwargs)

    @contextmanager
    def importing(self, name: str) -> Iterator[None]:
        """Inside: an optional library that backend ``name`` imports only when it opens, found missing, is
        reported as :meth:`load` reports it (naming the extra)."""
        try:
            yield
        except ModuleNotFoundError as exc:
            raise self._missing(exc, name, self._backends[name]) from None

    def _missing(self, exc: ModuleNotFoundError, name: str, backend: Backend) -> Exception:
        if exc.name is None or exc.name.split(".")[0] == "optitac_edge":
            return exc
        return missing_extra(exc.name, f"the {name} {self.kind}", extra=backend.extra or None)
