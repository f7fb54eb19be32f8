"""rosbag2 directories: a checked reader and a chunked, crash-tolerant writer (no rclpy; rosbags does CDR/MCAP).

Reading: `BagReader` opens a bag directory (metadata.yaml versions 4-9, storage mcap or sqlite3) or a
single .mcap/.db3 file. It reads each storage file with rosbags' per-file readers rather than rosbags'
directory reader: the latter matches the storage's connections to metadata.yaml by their QoS text and
silently yields no messages when the two differ (measured: rosbag2's own test bags talker/,
convert_a/, rewriter_a/ read 0 of 20/150/150 messages that way, all of them per file).
Every failure (missing, truncated, corrupt, compressed, another serialisation format) is a `BagError`
with one line saying what and where. metadata.yaml is untrusted input: it is read with a size cap
(`METADATA_MAX_BYTES`), without YAML aliases and with a nesting limit (an alias bomb of a few kB would
otherwise expand to gigabytes), and every data file it lists must lie inside the bag directory (no
absolute paths, no `..`, no symlinks leading out), so a bag never makes the tools read another bag's data.

Writing: `BagWriter` writes metadata version 9 (what Jazzy's rosbag2 writes) with type names,
RIHS01 type hashes, message definitions and offered QoS profiles, so `ros2 bag info/play` accept the
bag. It splits into files by size and/or duration; after each finished file metadata.yaml is
rewritten (atomically) to list the finished files, so a killed writer loses at most the file it was
writing. With `atomic=True` the bag is built in a hidden temporary directory beside the target and
renamed into place by `close()`: a failed run never leaves a bag that looks complete.
A write error (or free space on the bag's filesystem falling below `min_free_bytes`, checked before each
message so that the file being written can still be closed) puts the writer in a failed state: the
error is raised, every later `write` raises it again, no new file is started and nothing already
written is deleted; `close()` then finishes the current file with every message accepted so far (or,
should that fail too, leaves its data where it is and says so).
"""
from __future__ import annotations

import logging
import errno
import os
import shutil
import sqlite3
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any
from collections.abc import Iterable, Iterator

import yaml
from rosbags.interfaces import (MessageDefinitionFormat, Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.errors import ReaderError, WriterError
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from rosbags.typesys.store import Typestore

log = logging.getLogger(__name__)

METADATA = 'metadata.yaml'
WRITE_VERSION = 9
READ_VERSIONS = range(4, 10)
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
SUFFIX = {'mcap': '.mcap', 'sqlite3': '.db3'}
_INF = QosTime(9223372036, 854775807)   # RMW_DURATION_INFINITE as rosbag2 writes it
METADATA_MAX_BYTES = 4 * 1024 * 1024     # a real metadata.yaml is a few kB (custom_data holds node parameters)
METADATA_MAX_DEPTH = 32                  # nesting of metadata.yaml (rosbag2 writes 6 levels)
MIN_FREE_BYTES = 8 * 1024 * 1024         # kept free while writing: closing a file flushes up to ~1-2 MB (mcap
                                         # chunk, sqlite page cache) plus indexes and metadata.yaml


class BagError(Exception):
    """A bag cannot be read or written; the message is one line saying what and where."""


def _qos(depth: int, reliable: bool, latched: bool = False) -> Qos:
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, _INF, _INF,
               QosLiveliness.AUTOMATIC, _INF, False)


# QoS of the contract's topics (ARCHITECTURE.md), as offered profiles in bag metadata
SENSOR = _qos(5, reliable=False)
RELIABLE = _qos(10, reliable=True)
LATCHED = _qos(1, reliable=True, latched=True)
LANDING = _qos(100, reliable=True)

# topic -> (type, offered QoS): the default recorded set (every contract topic but /clock)
CONTRACT_TOPICS: dict[str, tuple[str, Qos]] = {
    '/camera/color/image_raw': ('sensor_msgs/msg/Image', SENSOR),
    '/camera/depth/image_raw': ('sensor_msgs/msg/Image', SENSOR),
    '/camera/color/camera_info': ('sensor_msgs/msg/CameraInfo', SENSOR),
    '/odom': ('nav_msgs/msg/Odometry', SENSOR),
    '/pilot/cmd_vel': ('geometry_msgs/msg/TwistStamped', RELIABLE),
    '/assist/latent': ('std_msgs/msg/Float32MultiArray', SENSOR),
    '/assist/pad_estimate': ('geometry_msgs/msg/PointStamped', SENSOR),
    '/assist/depth_denoised': ('sensor_msgs/msg/Image', SENSOR),
    '/assist/agent_cmd': ('geometry_msgs/msg/TwistStamped', RELIABLE),
    '/cmd_vel': ('geometry_msgs/msg/TwistStamped', RELIABLE),
    '/assist/goal_estimate': ('geometry_msgs/msg/PoseWithCovarianceStamped', RELIABLE),
    '/assist/descent_ok': ('std_msgs/msg/Bool', RELIABLE),
    '/uav/landed_state': ('std_msgs/msg/UInt8', LATCHED),
    '/sim/goal': ('geometry_msgs/msg/PointStamped', LATCHED),
    '/sim/landing': ('std_msgs/msg/String', LANDING),
    '/sim/scene': ('visualization_msgs/msg/MarkerArray', LATCHED),
    '/diagnostics': ('diagnostic_msgs/msg/DiagnosticArray', RELIABLE),
}


# custom_data that bag_record writes: assist.params.<node> -> JSON object of the node's parameters when the recorder
# reached it; assist.record_clock -> 'sim' (receive times are sim time) or 'wall'
PARAMS_KEY = 'assist.params.'
VELOCITY_FRAME_KEY = 'assist.velocity_frame'   # custom_data: 'odom' when the assistant saw world-frame velocity
DEPTH_NOISE_KEY = 'assist.depth_noise_seed'     # custom_data: '<base>,<landing>' seeds of the encoder's depth noise
CLOCK_KEY = 'assist.record_clock'


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy message definitions (rosbags' built-in store)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class TopicInfo:
    """One topic of a bag: type, message count, offered QoS and the bag's message definition."""

    name: str
    msgtype: str
    count: int = 0
    qos: list[Qos] = field(default_factory=list)
    msgdef: str = ''
    msgdef_format: MessageDefinitionFormat = MessageDefinitionFormat.NONE
    digest: str = ''


class _MetadataLoader(yaml.SafeLoader):
    """SafeLoader for untrusted metadata.yaml: no aliases (no alias bombs) and a nesting limit."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        """Compose one node; refuses aliases and documents nested deeper than METADATA_MAX_DEPTH."""
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, f'YAML aliases (*{event.anchor}) are not allowed',
                                              event.start_mark)
        self._depth += 1
        try:
            if self._depth > METADATA_MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f'nested deeper than {METADATA_MAX_DEPTH} levels',
                                                  self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def load_metadata_yaml(file: Path) -> Any:
    """Parse a metadata.yaml with limits (size cap, no aliases, nesting limit); BagError with one line."""
    try:
        with open(file, 'rb') as fh:
            raw = fh.read(METADATA_MAX_BYTES + 1)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise BagError(f'{file}: unreadable bag metadata ({exc.strerror})') from None
    if len(raw) > METADATA_MAX_BYTES:
        raise BagError(f'{file}: bag metadata larger than {METADATA_MAX_BYTES // (1024 * 1024)} MiB; not a '
                       f'rosbag2 metadata.yaml')
    try:
        return yaml.load(raw.decode('utf-8'), Loader=_MetadataLoader)  # a SafeLoader subclass
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise BagError(f'{file}: unreadable bag metadata ({_one_line(exc)})') from None


def _inside(bag: Path, name: str) -> Path:
    """The data file `name` of the bag at `bag`; BagError unless it lies inside the bag directory."""
    rel = Path(name)
    if not name or rel.is_absolute() or '..' in rel.parts:
        raise BagError(f'{bag}: {METADATA} lists data file {name!r} outside the bag directory; refusing it')
    path = bag / rel
    try:
        inside = path.resolve().is_relative_to(bag.resolve())
    except (OSError, RuntimeError):      # a symlink loop
        inside = False
    if not inside:
        raise BagError(f'{bag}: {METADATA} lists data file {name!r}, which leads outside the bag directory '
                       f'(a symlink); refusing it')
    return path


def _load_metadata(path: Path) -> dict:
    try:
        data = load_metadata_yaml(path / METADATA)
        info = data['rosbag2_bagfile_information']
        version = int(info['version'])
        storage = str(info['storage_identifier'])
        files = info['relative_file_paths']
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise TypeError('relative_file_paths is not a list of file names')
    except FileNotFoundError:
        raise BagError(f'{path}: not a bag (no {METADATA})') from None
    except (KeyError, TypeError, ValueError) as exc:
        raise BagError(f'{path}/{METADATA}: unreadable bag metadata ({type(exc).__name__}: {exc})'.splitlines()[0]
                       ) from None
    if version not in READ_VERSIONS:
        raise BagError(f'{path}: metadata version {version} is not supported (4 to 9 are)')
    if storage not in STORAGES:
        raise BagError(f'{path}: storage {storage!r} is not supported (mcap, sqlite3)')
    if info.get('compression_mode') or info.get('compression_format'):
        raise BagError(f'{path}: compressed bags are not supported; decompress it first '
                       f'(ros2 bag convert)')
    for f in files:
        _inside(path, f)
    info['relative_file_paths'] = files
    return info


class BagReader:
    """Read a rosbag2 bag (directory or single storage file); use as a context manager."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.metadata: dict = {}
        self.topics: dict[str, TopicInfo] = {}
        self._readers: list[Reader] = []
        if self.path.is_dir():
            self.metadata = _load_metadata(self.path)
            self.files = [_inside(self.path, f) for f in self.metadata['relative_file_paths']]
            missing = [f.name for f in self.files if not f.is_file()]
            if missing:
                raise BagError(f'{self.path}: data file(s) {", ".join(missing)} listed in {METADATA} are missing')
        elif self.path.is_file() and self.path.suffix in ('.mcap', '.db3'):
            self.files = [self.path]
        elif not self.path.exists():
            raise BagError(f'{self.path}: no such bag')
        else:
            raise BagError(f'{self.path}: not a bag (a directory with {METADATA}, or a .mcap/.db3 file)')

    # ------------------------------------------------------------------ open / close
    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open every storage file and collect the topics; BagError when a file is unreadable."""
        listed = self.metadata.get('topics_with_message_count')
        for t in listed if isinstance(listed, list) else []:
            tm = (t.get('topic_metadata', {}) if isinstance(t, dict) else {}) or {}
            fmt = tm.get('serialization_format', 'cdr') if isinstance(tm, dict) else 'cdr'
            if fmt != 'cdr':
                raise BagError(f'{self.path}: topic {tm.get("name")} is serialised as {fmt!r}, not cdr')
        for f in self.files:
            try:
                r = Reader(f)
                r.open()
            except (ReaderError, sqlite3.Error, OSError, ValueError, KeyError, IndexError) as exc:
                self.close()
                raise BagError(f'{f}: unreadable or truncated bag file ({_one_line(exc)})') from None
            self._readers.append(r)
            for c in r.connections:
                fmt = getattr(c.ext, 'serialization_format', 'cdr')
                if fmt != 'cdr':
                    self.close()
                    raise BagError(f'{f}: topic {c.topic} is serialised as {fmt!r}, not cdr')
                info = self.topics.get(c.topic)
                if info is None:
                    info = self.topics[c.topic] = TopicInfo(
                        c.topic, c.msgtype, qos=list(getattr(c.ext, 'offered_qos_profiles', []) or []),
                        msgdef=c.msgdef.data if c.msgdef else '',
                        msgdef_format=c.msgdef.format if c.msgdef else MessageDefinitionFormat.NONE,
                        digest=c.digest or '')
                elif info.msgtype != c.msgtype:
                    self.close()
                    raise BagError(f'{self.path}: topic {c.topic} has two types ({info.msgtype}, {c.msgtype})')
                if not info.msgdef and c.msgdef and c.msgdef.data:
                    info.msgdef, info.msgdef_format = c.msgdef.data, c.msgdef.format
                info.count += int(c.msgcount)

    def close(self) -> None:
        """Close the storage files."""
        for r in self._readers:
            try:
                r.close()
            except Exception:  # aborting after an error must not hide that error
                log.debug('closing %s failed', r.path, exc_info=True)
        self._readers = []

    # ------------------------------------------------------------------ content
    @property
    def message_count(self) -> int:
        """Messages in the bag (from the storage files' indexes)."""
        return sum(t.count for t in self.topics.values())

    @property
    def start_ns(self) -> int:
        """Earliest receive timestamp (ns); 0 for an empty bag."""
        starts = [r.start_time for r in self._readers if r.message_count]
        return min(starts) if starts else 0

    @property
    def end_ns(self) -> int:
        """Latest receive timestamp (ns); 0 for an empty bag."""
        ends = [r.end_time for r in self._readers if r.message_count]
        return max(ends) - 1 if ends else 0   # rosbags' end_time is one past the last message

    def select(self, topics: Iterable[str] | None) -> list[str]:
        """The bag's topics among `topics` (None: all); BagError when that leaves none."""
        if topics is None:
            return sorted(self.topics)
        wanted = list(topics)
        chosen = [t for t in wanted if t in self.topics]
        if not chosen:
            raise BagError(f'{self.path}: none of the selected topics {wanted} is in the bag '
                           f'(it has {sorted(self.topics)})')
        return chosen

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None
                 ) -> Iterator[tuple[str, int, bytes]]:
        """(topic, receive time ns, CDR bytes) in time order across files; BagError on a damaged file."""
        wanted = set(self.topics if topics is None else topics)
        for r in self._readers:
            conns = [c for c in r.connections if c.topic in wanted]
            if not conns:
                continue
            try:
                for c, t, raw in r.messages(connections=conns, start=start_ns):
                    yield c.topic, t, bytes(raw)
            except (ReaderError, sqlite3.Error, OSError, ValueError, KeyError, IndexError) as exc:
                raise BagError(f'{r.path}: damaged bag file ({_one_line(exc)})') from None

    def check_definitions(self, topics: Iterable[str]) -> None:
        """BagError when the bag's definition of a topic's type differs from this install's (another distro)."""
        ts = typestore()
        for name in topics:
            info = self.topics[name]
            if info.msgtype not in ts.types:
                continue
            if info.msgdef_format is not MessageDefinitionFormat.MSG or not info.msgdef.strip():
                continue   # no definition in the bag (older storage): trust the type name
            try:
                theirs = get_typestore(Stores.EMPTY)
                theirs.register(get_types_from_msg(info.msgdef, info.msgtype))
                same = theirs.hash_rihs01(info.msgtype) == ts.hash_rihs01(info.msgtype)
            except Exception as exc:  # noqa: BLE001 - any parse failure means: not our definition
                raise BagError(f'{self.path}: topic {name}: the bag\'s definition of {info.msgtype} cannot be '
                               f'parsed ({_one_line(exc)})') from None
            if not same:
                raise BagError(f'{self.path}: topic {name}: the bag\'s {info.msgtype} differs from this install\'s '
                               f'(ROS 2 Jazzy) definition: recorded with other message definitions')

    def deserialize(self, raw: bytes, topic: str) -> Any:
        """CDR bytes of `topic` -> rosbags message object (Jazzy definitions); BagError when undecodable."""
        msgtype = self.topics[topic].msgtype
        try:
            return typestore().deserialize_cdr(raw, msgtype)
        except KeyError:
            raise BagError(f'{self.path}: topic {topic}: type {msgtype} is unknown to this install') from None
        except Exception as exc:  # noqa: BLE001 - rosbags raises several types for bad CDR
            raise BagError(f'{self.path}: topic {topic}: undecodable {msgtype} message ({_one_line(exc)})'
                           ) from None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f'{type(exc).__name__}: {text[0] if text else ""}'.rstrip(': ')


# ---------------------------------------------------------------------------------------------- writing
STORAGE_ERRORS = (WriterError, OSError, sqlite3.Error)    # what the storages raise on a failed write


def free_bytes(path: str | Path) -> int:
    """Bytes an unprivileged writer may still use on the filesystem holding `path`."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def check_output(path: str | Path) -> None:
    """BagError unless `path` does not exist yet and could be created (checked before any long work)."""
    path = Path(path)
    if path.exists():
        raise BagError(f'{path}: exists already; not overwriting')
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise BagError(f'{path}: cannot be created ({parent} is not a writable directory)')


def publish_new(tmp: Path, dst: Path) -> None:
    """Move the finished temporary file `tmp` to `dst` unless `dst` exists (never overwrites, even in a race)."""
    try:
        os.link(tmp, dst)
    except FileExistsError:
        raise BagError(f'{dst}: exists already; not overwriting') from None
    except OSError as exc:
        raise BagError(f'{dst}: cannot write ({exc.strerror})') from None
    finally:
        tmp.unlink(missing_ok=True)


class BagWriter:
    """rosbag2 writer (metadata v9) with size/duration splitting and a crash-tolerant metadata.yaml."""

    def __init__(self, path: str | Path, storage: str = 'mcap', split_size_bytes: int = 0,
                 split_duration_ns: int = 0, atomic: bool = False, min_free_bytes: int = MIN_FREE_BYTES):
        if storage not in STORAGES:
            raise BagError(f'storage must be mcap or sqlite3, got {storage!r}')
        if split_size_bytes < 0 or split_duration_ns < 0:
            raise BagError('split sizes must be >= 0 (0: no split)')
        if min_free_bytes < 0:
            raise BagError('min_free_bytes must be >= 0')
        self.min_free = int(min_free_bytes)
        self.failed: BagError | None = None     # the first write error: the bag takes nothing more
        self.final = Path(path)
        self.storage = storage
        self.split_size = int(split_size_bytes)
        self.split_duration = int(split_duration_ns)
        self.atomic = atomic
        if self.final.exists():
            raise BagError(f'{self.final}: exists already; not overwriting a bag')
        parent = self.final.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BagError(f'{parent}: cannot create output directory ({exc.strerror})') from None
        if not os.access(parent, os.W_OK):
            raise BagError(f'{parent}: output directory is not writable')
        free = free_bytes(parent) if self.min_free else 0
        if free < self.min_free:
            raise BagError(f'{parent}: disk full: {free / 1e6:.1f} MB free, less than the {self.min_free / 1e6:.1f} MB '
                           f'a bag keeps free')
        self.path = parent / f'.{self.final.name}.partial-{os.getpid()}' if atomic else self.final
        try:
            self.path.mkdir()
        except OSError as exc:
            raise BagError(f'{self.path}: cannot create bag directory ({exc.strerror})') from None
        self.name = self.final.name
        self._topics: dict[str, tuple[str, list[Qos], Typestore | None, str | None, str | None]] = {}
        self._files: list[dict] = []          # finished files' metadata
        self._topic_meta: dict[str, dict] = {}
        self._writer: Writer | None = None
        self._conns: dict[str, Any] = {}
        self._chunk_dir: Path | None = None
        self._chunk_bytes = 0
        self._chunk_start: int | None = None
        self._chunk_count = 0
        self.closed = False
        self.custom_data: dict[str, str] = {}
        self._write_metadata()                # a valid (empty) bag from the start
        self.messages = 0                     # messages accepted (each is kept by close())

    # ------------------------------------------------------------------ topics
    def add_topic(self, topic: str, msgtype: str, qos: Qos | list[Qos] | None = None,
                  msgdef: str | None = None, digest: str | None = None) -> None:
        """Register a topic (type from this install's Jazzy store unless msgdef+digest are given)."""
        if topic in self._topics:
            return
        if msgdef is None and msgtype not in typestore().types:
            raise BagError(f'type {msgtype} of {topic} is unknown to this install')
        profiles = [qos] if isinstance(qos, Qos) else list(qos or [RELIABLE])
        self._topics[topic] = (msgtype, profiles, None if msgdef else typestore(), msgdef, digest)
        if self._writer is not None:
            self._add_conn(topic)

    def _add_conn(self, topic: str) -> None:
        msgtype, profiles, ts, msgdef, digest = self._topics[topic]
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=ts, msgdef=msgdef, rihs01=digest, offered_qos_profiles=profiles)

    def set_custom_data(self, key: str, value: str) -> None:
        """Set one custom_data entry of metadata.yaml and rewrite it now (a killed recorder keeps it too)."""
        if self.closed:
            raise BagError(f'{self.final}: bag already closed')
        if self.failed is not None:
            raise self.failed
        self.custom_data[str(key)] = str(value)
        self._write_metadata()

    # ------------------------------------------------------------------ messages
    def write(self, topic: str, t_ns: int, raw: bytes) -> None:
        """Append one CDR-serialised message received at `t_ns`; BagError (and the writer fails) on a write error."""
        if self.closed:
            raise BagError(f'{self.final}: bag already closed')
        if self.failed is not None:
            raise self.failed
        if topic not in self._topics:
            raise BagError(f'{topic}: add_topic first')
        t_ns = int(t_ns)
        if self._writer is not None and self._chunk_start is not None and (
                (self.split_size and self._chunk_bytes >= self.split_size) or
                (self.split_duration and t_ns - self._chunk_start >= self.split_duration)):
            self._finish_chunk()
        self._check_space(len(raw))
        if self._writer is None:
            self._start_chunk()
        if self._chunk_start is None:
            self._chunk_start = t_ns
        try:
            self._writer.write(self._conns[topic], t_ns, raw)
        except STORAGE_ERRORS as exc:
            raise self._fail(f'write failed ({_one_line(exc)})') from None
        self._chunk_bytes += len(raw)
        self._chunk_count += 1
        self.messages += 1

    def _fail(self, what: str) -> BagError:
        """Enter the failed state (first error wins); returns the error to raise."""
        if self.failed is None:
            self.failed = BagError(f'{self.path}: {what}')
        return self.failed

    def _check_space(self, size: int) -> None:
        """Fail before the storage sees a message that would leave less than min_free_bytes free."""
        if not self.min_free:
            return
        try:
            free = free_bytes(self.path)
        except OSError as exc:
            raise self._fail(f'cannot check free space ({exc.strerror})') from None
        if free - size < self.min_free:
            raise self._fail(f'disk full: {free / 1e6:.1f} MB free, less than the {self.min_free / 1e6:.1f} MB kept '
                             f'for closing the bag ({errno.errorcode[errno.ENOSPC]}); recording stopped')

    def write_msg(self, topic: str, t_ns: int, msg: Any) -> None:
        """Serialise a rosbags message object (Jazzy definitions) and append it."""
        self.write(topic, t_ns, bytes(typestore().serialize_cdr(msg, self._topics[topic][0])))

    # ------------------------------------------------------------------ chunks
    def _start_chunk(self) -> None:
        index = len(self._files)
        self._chunk_dir = self.path / f'.writing_{self.name}_{index}'
        if self._chunk_dir.exists():          # never reuse (and so delete) a file's data
            raise self._fail(f'{self._chunk_dir.name} exists already; not overwriting it')
        try:
            writer = Writer(self._chunk_dir, version=WRITE_VERSION, storage_plugin=STORAGES[self.storage])
            writer.open()
        except STORAGE_ERRORS as exc:
            raise self._fail(f'cannot write ({_one_line(exc)})') from None
        self._writer, self._conns = writer, {}
        for topic in self._topics:
            self._add_conn(topic)
        self._chunk_bytes, self._chunk_start, self._chunk_count = 0, None, 0

    def _finish_chunk(self) -> None:
        writer, self._writer = self._writer, None
        chunk = self._chunk_dir
        if writer is None or writer.storage is None:     # interrupted while opening: nothing to keep
            shutil.rmtree(chunk, ignore_errors=True)
            return
        if self._chunk_count == 0 and self._files:
            writer.abort()
            shutil.rmtree(chunk, ignore_errors=True)
            return
        try:
            writer.close()
            info = yaml.safe_load((chunk / METADATA).read_text(encoding='utf-8'))['rosbag2_bagfile_information']
            src = chunk / info['relative_file_paths'][0]
            dst_name = f'{self.name}_{len(self._files)}{SUFFIX[self.storage]}'
            os.replace(src, self.path / dst_name)
        except (*STORAGE_ERRORS, KeyError, yaml.YAMLError) as exc:
            # the unfinished file stays where it is (its data may still be recoverable): never deleted
            raise self._fail(f'closing a bag file failed ({_one_line(exc)}); its data is left in {chunk}') from None
        shutil.rmtree(chunk, ignore_errors=True)
        f = info['files'][0]
        self._files.append({'path': dst_name, 'starting_time': f['starting_time'], 'duration': f['duration'],
                            'message_count': f['message_count']})
        for t in info['topics_with_message_count']:
            name = t['topic_metadata']['name']
            if name in self._topic_meta:
                self._topic_meta[name]['message_count'] += t['message_count']
            else:
                self._topic_meta[name] = {'topic_metadata': t['topic_metadata'],
                                          'message_count': t['message_count']}
        self._write_metadata()

    def _write_metadata(self) -> None:
        files = [f for f in self._files if f['message_count']] or self._files
        starts = [f['starting_time']['nanoseconds_since_epoch'] for f in files if f['message_count']]
        ends = [f['starting_time']['nanoseconds_since_epoch'] + f['duration']['nanoseconds']
                for f in files if f['message_count']]
        start = min(starts) if starts else 0
        info = {
            'version': WRITE_VERSION,
            'storage_identifier': self.storage,
            'relative_file_paths': [f['path'] for f in self._files],
            'duration': {'nanoseconds': (max(ends) - start) if ends else 0},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': sum(f['message_count'] for f in self._files),
            'topics_with_message_count': list(self._topic_meta.values()),
            'compression_format': '',
            'compression_mode': '',
            'files': self._files,
            'custom_data': dict(self.custom_data) or None,
            'ros_distro': 'jazzy',
        }
        tmp = self.path / (METADATA + '.tmp')
        try:
            tmp.write_text(yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False), encoding='utf-8')
            os.replace(tmp, self.path / METADATA)
        except OSError as exc:     # the previous metadata.yaml (and every file it lists) is kept
            tmp.unlink(missing_ok=True)
            raise self._fail(f'cannot write {METADATA} ({exc.strerror})') from None

    # ------------------------------------------------------------------ end
    def close(self) -> Path:
        """Finish the last file, write metadata.yaml, move an atomic bag into place; returns its path.

        After a write error the current file is still finished with every message accepted before it (BagError
        only when that fails too; its data is then left in place); check `failed` for the error itself."""
        if self.closed:
            return self.final
        try:
            if self._writer is None and not self._files and self.failed is None:
                self._start_chunk()          # an empty bag still gets its (empty) storage file
            if self._writer is not None:
                self._finish_chunk()
        except BagError:
            if self.atomic:
                shutil.rmtree(self.path, ignore_errors=True)
            raise
        finally:
            self.closed = True
        if self.atomic and self.failed is not None:     # never a complete-looking bag from a failed run
            shutil.rmtree(self.path, ignore_errors=True)
            raise self.failed
        if self.atomic:
            if self.final.exists():
                raise BagError(f'{self.final}: appeared while writing; the new bag is left in {self.path}')
            os.replace(self.path, self.final)
        return self.final

    def abort(self) -> None:
        """Drop everything (atomic) or just the unfinished file (in place)."""
        if self._writer is not None:
            try:
                self._writer.abort()
            except Exception:  # aborting after an error must not hide that error
                log.debug('abort failed', exc_info=True)
            self._writer = None
            if self._chunk_dir is not None:
                shutil.rmtree(self._chunk_dir, ignore_errors=True)
        self.closed = True
        if self.atomic:
            shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
