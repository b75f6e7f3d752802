"""STATUS about once a period: each sensor's flags since its last STATUS and its camera's counters.

:class:`StatusReporter` sets every flag of a sensor's STATUS in one place
(:class:`~optitac_edge.io.protocol.messages.SensorState`), fills the sensor's
reused :class:`~optitac_edge.io.protocol.messages.StatusMessage`, hands it to the
link and offers it, with the same flags, to the network publisher.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from optitac_edge.io.protocol.messages import TEMP_UNKNOWN, SensorState, StatusMessage
from optitac_edge.io.protocol.outbox import LinkState
from optitac_edge.io.thermal import cpu_temperature_c
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.channel import SensorChannel
from optitac_edge.service.stats import ServiceStats

if TYPE_CHECKING:
    from optitac_edge.service.network import NetworkOutput


class StatusReporter:
    """The STATUS of every sensor of one camera.

    Parameters
    ----------
    channels : sequence of SensorChannel
    stats : ServiceStats
        The camera loop's counters.
    link : LinkState
        Streaming and protocol (STATUS bits 0 and 6).
    transport : Transport
        Where STATUS goes, and whose error counters it reports.
    period_s : float
        How often, seconds.
    """

    def __init__(self, channels: Sequence[SensorChannel], stats: ServiceStats, link: LinkState, transport: Transport,
                 period_s: float) -> None:
        self.channels, self.stats, self.link, self.transport = channels, stats, link, transport
        self.period_ns = int(period_s * 1e9)
        self.next_ns = 0
        #: The bundle could not be saved (the service runs on it from memory): STATUS bit5.
        self.calibration_unsaved = False

    def state(self, index: int = 0, camera_open: bool = True) -> SensorState:
        """The flags of sensor ``index`` for its STATUS (those since its last STATUS)."""
        ch = self.channels[index]
        return SensorState(streaming=self.link.streaming, baseline_ready=ch.pipeline.baseline_ready,
                           degraded=ch.degraded, camera_fault=(ch.fault_since_status or not camera_open
                                         or ch.mismatch is not None),
                           light_change=ch.light_since_status, calibration_unsaved=self.calibration_unsaved,
                           protocol_v2=self.link.protocol >= 2, protocol_v3=self.link.protocol == 3)

    def message(self, now_ns: int, index: int = 0, camera_open: bool = True,
                state: SensorState | None = None) -> StatusMessage:
        """The STATUS of sensor ``index`` (its flags since its last STATUS, then cleared)."""
        ch, st = self.channels[index], self.stats
        s = ch.status
        s.t_us = now_ns // 1000
        s.fps_x10 = round(st.recent_fps * 10)
        s.frames_dropped = st.frames_dropped
        s.camera_errors = st.camera_errors
        c = self.transport.counters
        s.link_errors = c.send_errors + c.rx_errors
        temp = cpu_temperature_c()
        s.cpu_temp_c_x10 = TEMP_UNKNOWN if temp is None else round(temp * 10)
        s.state = (self.state(index, camera_open) if state is None else state).bits
        ch.fault_since_status = ch.light_since_status = False
        return s

    def send(self, now_ns: int, camera_open: bool, network: NetworkOutput | None) -> None:
        """A STATUS for every sensor, with the frame rate of the last status period; the next in a period."""
        self.next_ns = now_ns + self.period_ns
        self.stats.measure_rate(now_ns)
        for k, ch in enumerate(self.channels):
            state = self.state(k, camera_open)
            status = self.message(now_ns, k, camera_open, state)
            packet = ch.outbox.status(status)
            if packet is not None:
                self.transport.send(packet)
            if network is not None:
                network.offer_status(ch.sensor_id, status, state, ch.frames, ch.contacts, self.stats.recent_fps,
                                     self.link.protocol)
