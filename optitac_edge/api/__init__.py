"""The public Python API: open a sensor, read its contacts frame by frame, tare it, close it.

Everything a script or a ROS 2 node needs, and the names the project promises to keep (``optitac_edge``
exports them; docs/api.md has examples). The modules below it are internal and may change.

    import optitac_edge as ot

    with ot.open_sensor("sim") as sensor:           # the built-in simulated sensor
        for reading in sensor.readings(duration_s=2.0):
            for c in reading.contacts:
                print(c.id, c.x_mm, c.y_mm, c.vx_mm_s, c.vy_mm_s, c.sliding)

A :class:`Sensor` reads its camera in the calling thread: each :meth:`Sensor.read` takes the next frame and
returns what it gave (a :class:`Reading`). It does not open the link to the MCU nor publish anything (that
is ``optitac-edge run``). The first frames of every session are the baseline (``baseline_ready`` False,
no contacts); a sensor without a calibration bundle calibrates its fiber map from its first rest frames,
as ``run`` does.
"""

from optitac_edge.api.readings import Contact, Reading, Status
from optitac_edge.api.sensor import Sensor, open_sensor
from optitac_edge.api.sensor_process import SensorProcess, open_sensor_process

__all__ = ["Contact", "Reading", "Sensor", "SensorProcess", "Status", "open_sensor", "open_sensor_process"]
