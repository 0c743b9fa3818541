"""Spec of the `recording` source stage. Declarations only."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import Recording
from eventcap.body.template import Template
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class RecordingConfig:
    path: str = param("", help="the recording: the project's zarr format, or a file or folder of any format a "
                               "reader takes (`eventcap formats` lists them)", file=True)
    format: str = param("", help="force a format: a name `eventcap formats` lists, or eventcap (the project's "
                                 "zarr); empty = detect from content/extension")
    t_start_s: float = param(0.0, ge=0, help="start of the time window, seconds from the first event")
    t_end_s: float = param(0.0, ge=0, help="end of the time window (0 = to the end)")
    roi: list[int] = param(default_factory=list, ge=0, help="region of interest [x0, y0, x1, y1] (external formats)")
    calibration: str = param("", help="rpg calib.txt overriding the file's calibration", file=True)
    width: int = param(0, ge=0, help="sensor width for formats that do not store it (0 = from the file)")
    height: int = param(0, ge=0, help="sensor height for formats that do not store it (0 = from the file)")
    time_unit: str = param("", help="unit of array/text time columns when the default (integers us, floats s) is "
                                    "wrong: s | ms | us | ns")
    columns: list[str] = param(default_factory=list, help="column order of unnamed array/text columns, e.g. "
                                                          "[x, y, t, p] (empty = names in the file or the "
                                                          "time-ordered column)")
    y_up: bool = param(False, help="the file's y axis points up (origin bottom-left): events are flipped")
    max_gap_s: float = param(0.0, ge=0, help="the longest pause between neighbouring events taken as real, seconds; "
                                             "0 = the default: 60 s, and a few events cut off by a jump long for "
                                             "the events' pace are dropped as outliers. A longer jump in time is "
                                             "refused, or repaired when it is a few wild timestamps or a decoder's "
                                             "artefact (the log says which)")
    frames: bool = param(True, help="false: leave the file's intensity frames out (use it as an event-only "
                                    "recording)")
    batch_rate_hz: float = param(25.0, gt=0, help="without intensity frames: batches of 1/rate from the first event (the "
                                            "times images are reconstructed at, pipeline=events_only)")
    up: str = param("person", help="world frame of a recording whose camera has no extrinsics: person (y up along "
                                   "the person's vertical, which the detect stage measures from the 3D detections; "
                                   "until then, and when it cannot, the camera assumed level at the origin, looking "
                                   "along -z) | level (the camera level, or tilted by camera_pitch_deg and "
                                   "camera_roll_deg: kept as given) | camera (the camera's own axes, y down)",
                    choices=("person", "level", "camera"))
    camera_pitch_deg: float = param(0.0, help="the camera's tilt, degrees (negative: looking down); given, it is "
                                              "kept (the world is not turned to the person's vertical)")
    camera_roll_deg: float = param(0.0, help="the camera's roll about its axis, degrees (positive: "
                                             "the world's up appears turned clockwise in the image)")


RECORDING = StageSpec(
    name="recording", kind="source", version=5,
    description="a recording from a file (real cameras' formats or the project's own), cut into batches",
    config=RecordingConfig, inputs={"template": Port(Template, optional=True)},
    outputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
    run="eventcap_recording._impl:run_recording", check="eventcap_recording.spec:check_config",
)


def check_config(config, where: str = "source") -> None:
    """The spec's ``check`` hook, before anything runs: a calibration file that is not an rpg calib.txt is refused
    (read only when it is a small regular file), and a format no registered reader takes. Whether ``path`` exists
    is the file settings' check."""
    if config.calibration:
        from eventcap.camera import check_rpg_calibration

        check_rpg_calibration(config.calibration, f"{where}.calibration")
    if config.format and config.format.lower() != "eventcap":
        from eventcap.io.registry import readers

        registry = readers()
        if config.format.lower() not in registry:
            from eventcap.names import unknown_name_message

            raise ValueError(f"{where}.format: " + unknown_name_message(
                "format", config.format, [*registry.names(), "eventcap"], "the recording readers (eventcap formats)"))
