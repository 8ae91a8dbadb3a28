"""Runtime settings: one TOML file, every setting also a command-line flag.

TOML layout (all keys optional; defaults below)::

    [laser]                     # names of the ROS urg_node driver
    ip_address = "192.168.0.10"
    ip_port = 10940
    serial_port = ""            # set for USB models (e.g. /dev/ttyACM0); wins over ip_address
    laser_frame_id = "laser"
    [base]                      # names of the ROS RosAria driver
    port = "/dev/ttyUSB0"       # serial device, or HOST:PORT for a TCP simulator
    baud = 9600
    ...

Each key ``section.name`` is also the flag ``--section.name VALUE`` (e.g. ``--laser.ip_address 10.0.0.5``);
flags win over the file, the file wins over the defaults. ``--laser URL`` / ``--base URL`` (full transport
URLs) win over the address keys.
"""

from __future__ import annotations

import argparse
import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A configuration file or flag is wrong; the message names the file, the key and the problem."""


def setting(default: Any, help: str) -> Any:
    """A config field with its default and the help text its command-line flag shows."""
    return field(default=default, metadata={"help": help})


@dataclass
class LaserConfig:
    """Hokuyo settings (ROS urg_node parameter names)."""

    ip_address: str = setting("192.168.0.10", "laser IP address (the UTM-30LX-EW's factory address)")
    ip_port: int = setting(10940, "laser TCP port")
    serial_port: str = setting("", "laser serial device for USB models (e.g. /dev/ttyACM0); wins over ip_address")
    serial_baud: int = setting(115200, "laser serial baud rate")
    laser_frame_id: str = setting("laser", "frame id of the laser in the recording")
    cluster: int = setting(1, "SCIP cluster count (adjacent steps merged)")
    skip: int = setting(0, "SCIP skip count (scans skipped between two sent)")
    multi_echo: str = setting("auto", "stream multi-echo scans (SCIP NE): auto = when the glass classifier reads "
                                      "echoes (the default context model does), on, off (ME: one echo; the "
                                      "classifier then falls back to the baseline model)")

    def url(self) -> str:
        if self.serial_port:
            return f"serial://{self.serial_port}?baud={self.serial_baud}"
        return f"tcp://{self.ip_address}:{self.ip_port}"


@dataclass
class BaseConfig:
    """Pioneer settings (ROS RosAria parameter names where they exist)."""

    port: str = setting("/dev/ttyUSB0", "base serial device, or HOST:PORT of a TCP simulator (RosAria 'port')")
    baud: int = setting(9600, "base serial baud rate at connection (the P3-DX powers up at 9600)")
    odom_frame: str = setting("odom", "odometry frame id")
    base_link_frame: str = setting("base_link", "robot base frame id")
    max_v: float = setting(0.5, "speed limit for commanded forward velocity (m/s)")
    max_omega: float = setting(1.0472, "speed limit for commanded rotation (rad/s)")
    enable_motors: bool = setting(False, "enable the motors at connection (needed to drive; off = never moves)")
    lost_hold: float = setting(5.0, "while the pose track is lost, hold the robot at rest up to this long (s; "
                               "the emulated robot's with --speed) for the estimator to relocalise against the "
                               "map, then drive on; if it does not, stop the run and say why (0: stop at once)")
    max_sigma: float = setting(1.0, "stop a driven run when the reported position standard deviation (m, its "
                               "widest direction; the pose graph's corrected estimate with loop closure) "
                               "exceeds this: no route can be followed on it (0: never)")

    def url(self) -> str:
        if self.port.startswith("/"):
            return f"serial://{self.port}?baud={self.baud}"
        host, sep, port = self.port.rpartition(":")
        if not sep or not port.isdigit():
            raise ConfigError(f"base.port {self.port!r}: expected a device path (/dev/ttyUSB0) or HOST:PORT")
        return f"tcp://{host}:{port}"


@dataclass
class MappingConfig:
    """Glass mapping and pose estimation settings."""

    map_frame: str = setting("map", "map frame id")
    registration: str = setting("robust", "glass registration: direct | robust")
    window: int = setting(3, "robust registration window k (3 or 5)")
    registration_sigma: str = setting("map", "registration sigma from the pose's covariance relative to the 'map' "
                                      "built so far, or relative to the map frame's 'anchor' (the reported one)")
    aggregation: str = setting("scan", "evidence aggregation per cell: scan | beam")
    decay_reference: str = setting("cell", "eq. 6 decay from the nearest occupied 'cell' or the beam 'endpoint'")
    visibility: bool = setting(True, "robust registration hands a beam's evidence to a window neighbour only as far "
                               "as the neighbour could have returned the beam (a pane the map believes in returns "
                               "only near normal incidence); false: eq. 6 as the paper prints it")
    occupancy_update: str = setting("mapper", "who integrates each scan into the occupancy grid at the corrected "
                                         "pose: 'mapper' (glass-aware: cells hit by glass-classified beams "
                                         "are kept occupied and not cleared) or 'estimator' (plain)")
    glass_scans: str = setting("keys", "which scans update the glass map (registration + Bayesian update): 'keys' "
                               "(each key scan, at the pose its match gave) or 'all' (every scan; between key scans "
                               "the pose comes from odometry since the last match); p(glass) per beam and the glass "
                               "hits kept occupied come from every scan either way")
    glass_weighting: bool = setting(True, "scan matching down-weights beams seen through cells the glass map "
                                    "believes are glass: what lies behind a pane, and the mirror images (ghost "
                                    "points) of panes the map holds as glass; panes seen only at grazing incidence "
                                    "are not in the glass map, so most mirror images are not caught")
    deskew: bool = setting(True, "undo the robot's motion during each laser sweep with the odometry before scan "
                            "matching (a real laser sweeps its 270 deg in ~19 ms; the demo's emulated laser "
                            "does not, so the demo turns this off)")
    max_free_range: float = setting(20.0, "a beam clears free space at most this far (m); glass lets beams through")
    no_return_range: float = setting(0.0, "a beam with no return (+inf) clears free space this far (m); 0 = not at all "
                                     "(near glass 'no return' often means the pulse was reflected away; 20 m "
                                     "made the office glass map's error 37 % instead of 12 %)")
    hit_margin: float = setting(0.2, "a beam with a return at the edge of a surface (a range jump, long range, "
                                "grazing incidence) clears free space only up to this far short of its end point "
                                "(m; at least one cell): clearing closer erases the near side of surfaces seen "
                                "obliquely, and the map comes out stretched along the route")
    surface_margin: float = setting(0.1, "the same for a beam inside a continuous surface (its neighbours 3 beams "
                                    "either side less than 0.3 m apart; m, at least one cell): a long margin there "
                                    "leaves the surface's free side unknown, and the map comes out shrunk")
    keyframe_distance: float = setting(0.05, "motion filter: scan matching and the occupancy update run on a scan only "
                                        "when the base moved this far (m) since the last key scan (0 with "
                                        "keyframe_angle_deg 0 = every scan); every scan still gets a pose and "
                                        "p(glass) per beam")
    keyframe_angle_deg: float = setting(2.0, "motion filter: ... or turned this much (deg) since the last key scan")
    keyframe_max_scans: int = setting(20, "motion filter: ... or this many scans passed since it (0 = no limit)")
    classifier_weights: str = setting("", "classifier weights stem (path without .pt/.json); '' = the shipped weights")
    laser_x: float = setting(0.1, "laser mount in the base frame: x (m, forward of the axle)")
    laser_y: float = setting(0.0, "laser mount in the base frame: y (m, left)")
    laser_yaw: float = setting(0.0, "laser mount in the base frame: yaw (rad)")
    loop_closure: bool = setting(False, "run the pose graph with loop closure behind the estimator in a worker "
                                 "process (records /pose/corrected, the estimate corrected by the graph with the "
                                 "graph's covariance, /pose_graph/path, /map/corrected)")
    initial_x: float = setting(0.0, "initial pose of the base in the map frame: x (m)")
    initial_y: float = setting(0.0, "initial pose of the base in the map frame: y (m)")
    initial_yaw: float = setting(0.0, "initial pose of the base in the map frame: yaw (rad)")


@dataclass
class PipelineConfig:
    """Processing stage settings."""

    queue_size: int = setting(8, "scans waiting for processing (8 = 200 ms at 40 Hz: a laser or event loop that "
                              "stalls and then delivers a burst); when full the oldest is dropped (and counted)")
    max_scan_age: float = setting(0.5, "a scan older than this (s, host clock) when processing starts is dropped "
                                  "(and counted) as stale")
    odom_buffer: int = setting(400, "odometry messages kept for interpolation")
    nice: int = setting(0, "niceness of the scan-processing thread (Linux; -20 first .. 19 last): below 0 puts "
                        "the scans before other programs on a busy laptop; needs CAP_SYS_NICE or 'ulimit -e' "
                        "(refused: a warning, default priority)")
    memory_reserve: int = setting(96, "MiB of memory written once at start-up and kept by the allocator (glibc), "
                                      "so the grid growing at the first scans does not wait for new pages; 0 = off")


@dataclass
class OutputConfig:
    """Files written by the runtime."""

    out_dir: str = setting("out/run", "directory for maps (PNG, .npy, PGM + YAML)")
    export_period: float = setting(10.0, "seconds between periodic map exports (0 = only at exit)")
    map_publish_period: float = setting(2.0, "seconds between /map and /glass/map messages in the recording")
    record: str = setting("", "MCAP file to record into ('' = no recording)")
    record_split_size: int = setting(0, "split the recording into files of about this many bytes (one chunk "
                                        "more at most): <stem>_0000.mcap, <stem>_0001.mcap, ...; 0 = no split")
    record_split_duration: float = setting(0.0, "split the recording every this many seconds (0 = no split)")
    record_raw: bool = setting(True, "record the raw device bytes (needed to replay through the drivers)")
    chunk_size: int = setting(512 * 1024, "MCAP chunk size (bytes): at most this much is lost on a crash")
    chunk_interval: float = setting(1.0, "MCAP chunk interval (s): chunks are closed at least this often")
    compression: str = setting("zstd", "MCAP chunk compression: zstd | lz4 | none")
    live: str = setting("", "serve the live view (Foxglove WebSocket) on [HOST:]PORT; loopback unless a host "
                            "is given ('' = off)")
    live_map_period: float = setting(1.0, "live view: seconds between two /map (and two /glass/map) messages")
    live_queue_size: int = setting(256, "live view: messages waiting to be sent; when full new ones are "
                                        "dropped (and counted)")


@dataclass
class RuntimeConfig:
    laser: LaserConfig = field(default_factory=LaserConfig)
    base: BaseConfig = field(default_factory=BaseConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    laser_url: str = ""
    base_url: str = ""

    def resolved_laser_url(self) -> str:
        return self.laser_url or self.laser.url()

    def resolved_base_url(self) -> str:
        return self.base_url or self.base.url()

    def validate(self) -> None:
        if self.laser.multi_echo not in ("auto", "on", "off"):
            raise ConfigError(f"laser.multi_echo must be auto, on or off, got {self.laser.multi_echo!r}")
        m = self.mapping
        if m.registration not in ("direct", "robust"):
            raise ConfigError(f"mapping.registration must be direct or robust, got {m.registration!r}")
        if m.window not in (3, 5):
            raise ConfigError(f"mapping.window must be 3 or 5, got {m.window}")
        if m.registration_sigma not in ("map", "anchor"):
            raise ConfigError(f"mapping.registration_sigma must be map or anchor, got {m.registration_sigma!r}")
        if m.aggregation not in ("scan", "beam"):
            raise ConfigError(f"mapping.aggregation must be scan or beam, got {m.aggregation!r}")
        if m.decay_reference not in ("cell", "endpoint"):
            raise ConfigError(f"mapping.decay_reference must be cell or endpoint, got {m.decay_reference!r}")
        if m.glass_scans not in ("keys", "all"):
            raise ConfigError(f"mapping.glass_scans must be keys or all, got {m.glass_scans!r}")
        if m.occupancy_update not in ("mapper", "estimator"):
            raise ConfigError(f"mapping.occupancy_update must be mapper or estimator, got {m.occupancy_update!r}")
        if m.max_free_range <= 0:
            raise ConfigError(f"mapping.max_free_range must be > 0 m, got {m.max_free_range}")
        if m.no_return_range < 0:
            raise ConfigError(f"mapping.no_return_range must be >= 0 m, got {m.no_return_range}")
        if m.hit_margin < 0 or m.surface_margin < 0:
            raise ConfigError(f"mapping.hit_margin and surface_margin must be >= 0 m, got {m.hit_margin} and "
                              f"{m.surface_margin}")
        if m.keyframe_distance < 0 or m.keyframe_angle_deg < 0 or m.keyframe_max_scans < 0:
            raise ConfigError("mapping.keyframe_distance (m), keyframe_angle_deg and keyframe_max_scans must be >= 0")
        if self.base.lost_hold < 0 or self.base.max_sigma < 0:
            raise ConfigError(f"base.lost_hold (s) and base.max_sigma (m) must be >= 0, got {self.base.lost_hold} "
                              f"and {self.base.max_sigma}")
        if self.pipeline.queue_size < 1:
            raise ConfigError("pipeline.queue_size must be >= 1")
        if not -20 <= self.pipeline.nice <= 19:
            raise ConfigError(f"pipeline.nice must be in -20 .. 19, got {self.pipeline.nice}")
        if self.pipeline.max_scan_age <= 0:
            raise ConfigError("pipeline.max_scan_age must be > 0 s")
        if self.pipeline.memory_reserve < 0:
            raise ConfigError(f"pipeline.memory_reserve must be >= 0 MiB, got {self.pipeline.memory_reserve}")
        if self.output.live:
            from runtime.output_args import LiveViewError, parse_address

            try:
                parse_address(self.output.live)
            except LiveViewError as exc:
                raise ConfigError(str(exc).replace("--live", "output.live", 1)) from None
        if self.output.record_split_size < 0 or self.output.record_split_duration < 0:
            raise ConfigError("output.record_split_size (bytes) and output.record_split_duration (s) must be >= 0")
        if self.output.live_map_period < 0 or self.output.live_queue_size < 1:
            raise ConfigError("output.live_map_period must be >= 0 s and output.live_queue_size >= 1")
        if self.output.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(f"output.compression must be zstd, lz4 or none, got {self.output.compression!r}")


SECTIONS = ("laser", "base", "mapping", "pipeline", "output")


def _coerce(value: Any, typ: type, where: str) -> Any:
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("1", "true", "yes", "on", "0", "false", "no", "off"):
            return value.lower() in ("1", "true", "yes", "on")
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if typ is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if typ is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if typ is str and isinstance(value, str):
        return value
    if isinstance(value, str):
        try:
            return typ(value)
        except ValueError:
            pass
    raise ConfigError(f"{where}: expected {typ.__name__}, got {value!r}")


def _field_types(cls) -> dict[str, type]:
    hints = {"str": str, "int": int, "float": float, "bool": bool}
    return {f.name: hints[f.type] if isinstance(f.type, str) else f.type for f in dataclasses.fields(cls)}


def load_config(path: str | Path | None, base: RuntimeConfig | None = None) -> RuntimeConfig:
    """Read a TOML file over the defaults (or over ``base``). Unknown sections or keys are errors."""
    cfg = base or RuntimeConfig()
    if path is None:
        return cfg
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a directory; --config takes a TOML file (e.g. {path / 'glassmap.toml'})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text (TOML) file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config file ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    for section, values in data.items():
        if section not in SECTIONS:
            raise ConfigError(f"{path}: unknown section [{section}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, dict):
            raise ConfigError(f"{path}: {section} must be a table [{section}]")
        obj = getattr(cfg, section)
        types = _field_types(type(obj))
        for key, value in values.items():
            if key not in types:
                raise ConfigError(f"{path}: unknown key {section}.{key} (known: {', '.join(types)})")
            setattr(obj, key, _coerce(value, types[key], f"{path}: {section}.{key}"))
    try:
        cfg.validate()
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return cfg


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` and one ``--section.key`` flag per setting (default: unset)."""
    parser.add_argument("--config", metavar="FILE", help="TOML settings file (flags win over it)")
    defaults = RuntimeConfig()
    for section in SECTIONS:
        obj = getattr(defaults, section)
        group = parser.add_argument_group(f"[{section}] settings ({type(obj).__doc__.strip()})")
        for f in dataclasses.fields(obj):
            typ = _field_types(type(obj))[f.name]
            default = getattr(obj, f.name)
            # SUPPRESS: unset flags leave no attribute (and no "(default: None)" in --help)
            group.add_argument(f"--{section}.{f.name}", dest=f"cfg__{section}__{f.name}", default=argparse.SUPPRESS,
                               metavar="BOOL" if typ is bool else typ.__name__.upper(),
                               help=f"{f.metadata.get('help', '')} (default: {default!r})".replace("%", "%%"))


def config_from_args(args: argparse.Namespace, base: RuntimeConfig | None = None) -> RuntimeConfig:
    """Defaults <- ``base`` <- ``--config`` file <- ``--section.key`` flags."""
    cfg = load_config(getattr(args, "config", None), base)
    for section in SECTIONS:
        obj = getattr(cfg, section)
        types = _field_types(type(obj))
        for name, typ in types.items():
            value = getattr(args, f"cfg__{section}__{name}", None)
            if value is not None:
                setattr(obj, name, _coerce(value, typ, f"--{section}.{name}"))
    cfg.validate()
    return cfg
