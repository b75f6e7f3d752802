"""What each command's ``--help`` says: what it does, and examples to start from (the bring-up guide's order).

Kept as data apart from the options (cantools' habit: the text is not logic), and
applied to the parser by :func:`describe`.
"""

from __future__ import annotations

import argparse
import textwrap

#: Per command ("calibrate fibers" for a step): a description, then example command lines.
COMMANDS: dict[str, tuple[str, list[str]]] = {
    "sim": (
        ("Write a recording from the built-in simulated sensor: rest frames, then presses with truth.csv. "
        "Scenarios: rest, demo, seen (a press over every fiber), unseen (0.25 mm steps along x and y), repeat, "
        "widths, shapes, drift (the LED dims), depths (known depths, with a load cell's force). --day and "
        "--variant give another session and another simulated sensor; --physics another guess at how the skin "
        "responds (docs/simulator.md)."),
        ["optitac-edge sim out/rest --scenario rest",
         "optitac-edge sim out/seen --scenario seen --seed 2",
         "optitac-edge sim out/depths --scenario depths --seed 5 --day 1",
         "optitac-edge sim out/depths-linear --scenario depths --physics linear --day 2",
         "optitac-edge sim out/seen61 --scenario seen --layout hex61.csv"]),
    "layout": (
        ("Write a hexagonal fiber array's layout CSV: a central fiber and rings of fibers at one pitch, rows "
         "along +x. Give it to 'calibrate fibers --layout', to '[calibration] layout' of a board, and to the "
         "simulator ('sim --layout', '[camera.options] layout') to bring up an array of another size."),
        ["optitac-edge layout --rings 4 --pitch-mm 4 -o hex61.csv",
         "optitac-edge layout --rings 18 --pitch-mm 1.5 -o hex1027.csv"]),
    "calibrate fibers": (
        ("Build a calibration bundle from a recording's rest frames: where every fiber of the layout is in the "
        "image, the surface grid and the noise-derived contact levels."),
        ["optitac-edge calibrate fibers out/rest -o out/cal.npz",
         "optitac-edge calibrate fibers rec/rest -o cal.npz --layout my_layout.csv --rotation-deg 30"]),
    "calibrate orientation": (
        ("Check the bundle's fiber map against presses of known position; fix a rotation or mirror of the "
        "layout (this removes the centroid, width and shape models: calibrate them again)."),
        ["optitac-edge calibrate orientation out/unseen --cal out/cal.npz"]),
    "calibrate levels": (
        ("Choose the contact levels from your own recordings: each fiber's rest excursion (its noise and its "
         "drift since the baseline, over every rest frame) gives it a band of its own, and the on level is put "
         "where rest and contact frames are best told apart, checked on presses and rest frames held out of the "
         "choice (detection and false contacts reported). Several recordings (days, sessions) each keep their "
         "own baseline; a recording's tare points are honoured. Without this step the levels come from the rest "
         "frames' noise."),
        ["optitac-edge calibrate levels rec/seen --cal cal.npz",
         "optitac-edge calibrate levels day1/presses day2/presses --cal cal.npz"]),
    "calibrate centroid": (
        ("Centroid error maps from presses of known position (a 'seen' recording or collection); the fill between "
         "presses is chosen by presses held out of the map."),
        ["optitac-edge calibrate centroid out/seen --cal out/cal.npz"]),
    "calibrate width": (
        ("The width model from circles of known diameter (a 'widths' recording or collection); its form is chosen "
         "by presses held out of the fit."),
        ["optitac-edge calibrate width out/widths --cal out/cal.npz"]),
    "calibrate shapes": (
        ("The shape classifier from labelled presses (a 'shapes' recording or collection); needs the "
        "calibrate extra (scikit-learn)."),
        ["optitac-edge calibrate shapes out/shapes --cal out/cal.npz"]),
    "calibrate depth": (
        ("The depth model from presses of known depth (a 'depths' recording or collection), and the force model "
        "where truth.csv has a load cell's force_n column; a rig without a load cell calibrates depth alone. "
        "The contact feature each model reads is chosen by presses held out of the fit; 56 presses or more. "
        "Needs the calibrate extra (scikit-learn)."),
        ["optitac-edge calibrate depth rec/depths --cal cal.npz      # after: collect depths -o rec/depths",
         "optitac-edge calibrate depth out/depths --cal out/cal.npz  # after: sim out/depths --scenario depths"]),
    "evaluate": (
        ("Accuracy of a bundle on a recording with truth.csv (detection, centroid, widths, shapes, depth), and a "
        "verdict on whether the calibration is good enough; --strict exits 1 when it is not."),
        ["optitac-edge evaluate out/unseen --cal out/cal.npz",
         "optitac-edge evaluate rec/unseen --cal cal.npz --strict"]),
    "export-onnx": (
        "Export the bundle's shape classifier to ONNX (for evaluate --shape-backend onnx or your own runtime).",
        ["optitac-edge export-onnx out/cal.npz -o out/shapes.onnx"]),
    "report": (
        "Write the calibration's figures (PNG) and a summary (index.md) into a directory.",
        ["optitac-edge report out/cal.npz -o out/report --unseen out/unseen --repeat out/repeat"]),
    "replay": (
        "Process every frame of a recording into a contacts CSV, as the service would.",
        ["optitac-edge replay out/unseen --cal out/cal.npz -o out/contacts.csv"]),
    "export-lerobot": (
        ("Write recordings as a LeRobot dataset with LeRobot's own writer, one episode each: every frame's "
         "contacts, vibration and per-fiber signals as named features, the capture time, the recording's truth "
         "where it has one, and with --video the tactile surface as a 224x224 video. Needs the lerobot extra "
         "(torch; docs/lerobot.md)."),
        ["optitac-edge export-lerobot out/seen out/slide --cal out/cal.npz -o out/dataset",
         "optitac-edge export-lerobot rec/day1 rec/day2 --cal cal.npz -o data/grasp --repo-id lab/grasp --video"]),
    "run": (
        ("The service: capture, process, send each frame's contacts to the MCU (serial or CAN) and, if asked, "
        "to the robot's network (Zenoh / ROS 2), an MCAP file and a live view. Without a board it runs the "
        "built-in simulated sensor. Ctrl-C stops it cleanly (exit 130); SIGTERM and SIGHUP exit 0."),
        ["optitac-edge run",
         "optitac-edge run --board rpi5-gs --serial /dev/ttyAMA0",
         "optitac-edge run --board sim-hand --view 127.0.0.1:8080 --mcap run.mcap"]),
    "record": (
        ("Save frames of a board's camera as a recording: by default the rest frames as they are and each "
        "fiber's light after them (--storage fibers, ~0.4 kB a frame); --storage raw keeps every frame."),
        ["optitac-edge record --board rpi5-gs -o rec/rest --frames 600",
         "optitac-edge record --board rpi5-gs -o rec/raw --frames 600 --storage raw"]),
    "soak": (
        ("Run the whole loop on the simulator with injected faults (camera errors, a serial unplug) and report "
        "recovery; --virtual-time runs on a virtual clock (same seed, same counts)."),
        ["optitac-edge soak --minutes 2 --virtual-time"]),
    "bench": (
        ("Measure the per-frame loop: stage timings, the reference method's ratio, memory, paced runs, main-"
        "thread CPU, end to end over a pty at --fps, start-up (docs/performance.md)."),
        ["optitac-edge bench --frames 20000 --json bench.json",
         "optitac-edge bench --e2e-seconds 60 --fps 240 --e2e-publish"]),
    "orient": (
        ("Find the layout's orientation from two presses by hand (near the +x edge, then near the +y edge) and "
        "write it into the bundle. On the simulated camera a simulated operator presses."),
        ["optitac-edge orient --board rpi5-gs", "optitac-edge orient --cal out/cal.npz -o out/cal.npz"]),
    "collect": (
        ("Run one of the paper's experiments on an indentation rig (a GRBL machine, a UR arm, or the simulator's "
        "virtual rig) into a recording with truth: rest, touch-off, registration, the presses, then the tip "
        "parks at the safe height over the start point. An interrupted collection continues after its last "
        "press when run again; every way out retracts the tip."),
        ["optitac-edge collect seen --rig sim:// -o rec/seen",
         "optitac-edge collect depths --board bench.toml --rig gcode:///dev/ttyUSB0 -o rec/depths",
         "optitac-edge collect shapes --rig sim:// -o rec/shapes --limit 40"]),
    "monitor": (
        ("Sit where the MCU sits: show what it receives (CONTACT, CONTACT2, RELEASE, STATUS, ACK), rates, "
        "sequence gaps and errors, and send it the MCU's commands."),
        ["optitac-edge monitor --serial /dev/ttyUSB0 --send 'stream on' --all",
         "optitac-edge monitor --serial /dev/ttyUSB0 --send 'protocol 2'",
         "optitac-edge monitor --can can0"]),
    "view": (
        "Serve the live view (camera, fiber map, surface, contacts, actions) to any browser.",
        ["optitac-edge view", "optitac-edge view --board rpi5-gs --bind 0.0.0.0:8080"]),
    "snapshot": (
        "Write the live view's picture of a board's camera to a PNG.",
        ["optitac-edge snapshot --board rpi5-gs -o shot.png"]),
}

#: Help of arguments that had none, by command and option (dest for positionals).
ARGUMENTS: dict[str, dict[str, str]] = {
    "sim": {"out_dir": "the recording to write (a directory, or NAME.mcap for one MCAP file)",
            "--seed": "seed of the presses and the noise (default 0)",
            "--width": "image width, px (default 640)", "--height": "image height, px (default 480)"},
    "evaluate": {"recording": "a recording with truth.csv (directory or .mcap)", "--cal": "the bundle to evaluate",
                 "--shape-backend": "evaluate the shape model in closed form (numpy) or with onnxruntime"},
    "export-onnx": {"cal": "the bundle", "--output": "the ONNX file to write"},
    "report": {"cal": "the bundle", "--output": "the directory to write the figures and index.md into"},
    "replay": {"recording": "the recording (directory or .mcap)", "--cal": "the bundle",
               "--output": "the contacts CSV to write"},
    "record": {"--output": "the recording to write (a directory, or NAME.mcap)",
               "--frames": "frames to record (default 300)"},
    "soak": {"--minutes": "how long to run (service time)", "--seed": "seed of the faults (default 0)",
             "--fps": "the simulated camera's frame rate (default 60)"},
    "collect": {"--output": "the recording to write (continued if it is an interrupted collection)"},
    "monitor": {"--baud": "serial baud rate (default 921600)", "--duration": "stop after S seconds"},
    "snapshot": {"--output": "the PNG to write"},
    "layout": {"--output": "the layout CSV to write"},
}
ARGUMENTS["calibrate fibers"] = {"recording": "the recording (directory or .mcap)"}


def describe(parser: argparse.ArgumentParser, name: str = "") -> None:
    """Give every command of ``parser`` its description, examples and missing argument help."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in dict(action.choices).items():
                describe(sub, f"{name} {sub_name}".strip())
    if name in COMMANDS:
        text, examples = COMMANDS[name]
        parser.description = textwrap.fill(text, width=100)
        parser.epilog = "examples:\n" + "\n".join(f"  {line}" for line in examples)
        parser.formatter_class = argparse.RawDescriptionHelpFormatter
    for action in parser._actions:
        key = next((o for o in action.option_strings if o.startswith("--")), action.dest)
        if not action.help and key in ARGUMENTS.get(name, {}):
            action.help = ARGUMENTS[name][key]
