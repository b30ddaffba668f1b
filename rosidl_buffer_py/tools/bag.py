"""MCAP bags in rosbag2's profile: the files ``buffer_record`` writes and ``buffer_play`` reads.

A bag is a directory ``<name>/`` holding ``<name>_0.mcap``, ``<name>_1.mcap``, ... (a new file
per split) and rosbag2's ``metadata.yaml``, as ``ros2 bag record -s mcap`` makes it. Each file
has the ``ros2`` profile: one ``ros2msg`` schema per type with its complete definition
(:mod:`.message_definition`), one ``cdr`` channel per topic with the metadata rosbag2 writes
(``offered_qos_profiles``: YAML of the publishers' QoS, ``topic_type_hash``), messages with log
time (reception) and publish time (the publisher's source timestamp), and a ``rosbag2`` metadata
record with the bag's metadata.

Files are chunked and indexed, as rosbag2's default MCAP profile writes them, so that a file cut
short (SIGKILL, crash, power loss, full disk) keeps every chunk written before the cut and
:mod:`.reindex` can finish it. Messages smaller than :data:`CHUNK_SIZE` are gathered into one
uncompressed chunk, written (and its message indexes after it) once it holds :data:`CHUNK_SIZE`
bytes or its first message is :data:`FLUSH_PERIOD_SEC` old; the file is ``fdatasync``'ed every
:data:`FLUSH_PERIOD_SEC` by a thread of its own (:class:`_Syncer`). A larger message is a chunk of
its own, written from where its payload is: :meth:`BagWriter.write` passes it straight from a
shared-memory Buffer to the kernel. A payload of at least :data:`DIRECT_MIN_BYTES` that is
page-aligned in memory (a demo backend frame) is written with ``O_DIRECT``: a private padding record
(opcode :data:`PADDING_OPCODE`, which MCAP readers skip) before its chunk puts it at a page boundary
of the file, and the disk reads it from shared memory without a copy into the page cache (that copy
costs 20 to 50 ms of CPU per 4K frame under sustained load; ``./dev bench record``). Other messages,
and file systems without ``O_DIRECT``, go through ``os.pwritev``.
The mcap library writes every other record (header, schemas, channels, metadata, summary,
footer); chunks and message indexes are written here, and entered into the library writer's
statistics and chunk indexes (:class:`_LibraryState`, the one place that reaches into it).
"""
import heapq
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple

import yaml
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, ChunkIndex, Message, MessageIndex
from mcap.summary import Summary
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy)

from rosidl_buffer_py.tools.message_definition import MessageDefinition

__all__ = [
    'BagError',
    'BagReader',
    'BagWriter',
    'Topic',
    'qos_from_yaml',
    'qos_to_yaml',
]

#: Version of rosbag2's metadata format written (Jazzy's).
METADATA_VERSION = 9
PROFILE = 'ros2'
STORAGE_ID = 'mcap'
SERIALIZATION_FORMAT = 'cdr'
#: Message record header: opcode, record length, channel id, sequence, log time, publish time.
_MESSAGE_HEADER = struct.Struct('<BQHIQQ')
_MESSAGE_FIXED = 2 + 4 + 8 + 8
#: Small records are gathered up to this many bytes before a write() system call.
_SMALL_WRITE = 64 * 1024
#: Messages smaller than this are gathered into one chunk of about this size (rosbag2's MCAP
#: default, 768 KiB); a larger message is a chunk of its own.
CHUNK_SIZE = 768 * 1024
#: A chunk is written once its first message is this old, and the file fdatasync'ed at most
#: this often: what a crash, SIGKILL or power cut can lose.
FLUSH_PERIOD_SEC = 1.0
#: Chunk record up to its data: opcode, record length, message start and end time, uncompressed
#: size, uncompressed CRC, compression (empty string: its length), compressed size.
_CHUNK_HEADER = struct.Struct('<BQQQQIIQ')
_CHUNK_FIXED = _CHUNK_HEADER.size - 9
_MAX_IOV = 512
#: Payloads of at least this size, page-aligned in memory, are written with O_DIRECT.
DIRECT_MIN_BYTES = 1024 * 1024
DIRECT_ALIGNMENT = 4096
#: Opcode of the private record that pads the file so that a payload starts page-aligned
#: (MCAP reserves 0x80-0xFF for private records; readers skip records they do not know).
PADDING_OPCODE = 0x80
_RECORD_PREFIX = struct.Struct('<BQ')


class BagError(Exception):
    """A bag that cannot be read or written; the message names the file and what is wrong."""


# --- QoS as rosbag2 writes it (rosbag2_storage/qos.cpp, metadata version 9) ---------------------

_HISTORY = {HistoryPolicy.KEEP_LAST: 'keep_last', HistoryPolicy.KEEP_ALL: 'keep_all',
            HistoryPolicy.SYSTEM_DEFAULT: 'system_default', HistoryPolicy.UNKNOWN: 'unknown'}
_RELIABILITY = {ReliabilityPolicy.RELIABLE: 'reliable',
                ReliabilityPolicy.BEST_EFFORT: 'best_effort',
                ReliabilityPolicy.SYSTEM_DEFAULT: 'system_default',
                ReliabilityPolicy.BEST_AVAILABLE: 'best_available',
                ReliabilityPolicy.UNKNOWN: 'unknown'}
_DURABILITY = {DurabilityPolicy.VOLATILE: 'volatile',
               DurabilityPolicy.TRANSIENT_LOCAL: 'transient_local',
               DurabilityPolicy.SYSTEM_DEFAULT: 'system_default',
               DurabilityPolicy.BEST_AVAILABLE: 'best_available',
               DurabilityPolicy.UNKNOWN: 'unknown'}
_LIVELINESS = {LivelinessPolicy.AUTOMATIC: 'automatic',
               LivelinessPolicy.MANUAL_BY_TOPIC: 'manual_by_topic',
               LivelinessPolicy.SYSTEM_DEFAULT: 'system_default',
               LivelinessPolicy.BEST_AVAILABLE: 'best_available',
               LivelinessPolicy.UNKNOWN: 'unknown'}
# Metadata versions before 9 stored the rmw enum values as integers.
_INTEGER_POLICIES = {'history': HistoryPolicy, 'reliability': ReliabilityPolicy,
                     'durability': DurabilityPolicy, 'liveliness': LivelinessPolicy}


def _duration(value: Duration) -> dict:
    sec, nsec = divmod(value.nanoseconds, 1_000_000_000)
    return {'sec': sec, 'nsec': nsec}


def qos_to_dict(profile: QoSProfile) -> dict:
    """One QoS profile as rosbag2 serializes it (``Rosbag2QoS``, version 9)."""
    return {
        'history': _HISTORY.get(profile.history, 'unknown'),
        'depth': int(profile.depth),
        'reliability': _RELIABILITY.get(profile.reliability, 'unknown'),
        'durability': _DURABILITY.get(profile.durability, 'unknown'),
        'deadline': _duration(profile.deadline),
        'lifespan': _duration(profile.lifespan),
        'liveliness': _LIVELINESS.get(profile.liveliness, 'unknown'),
        'liveliness_lease_duration': _duration(profile.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': bool(profile.avoid_ros_namespace_conventions),
    }


def qos_to_yaml(profiles: Sequence[QoSProfile]) -> str:
    """The ``offered_qos_profiles`` channel metadata: a YAML list of profiles."""
    if not profiles:
        return ''
    return yaml.safe_dump([qos_to_dict(p) for p in profiles], sort_keys=False)


def _policy(value, names: dict, enum, key: str):
    if isinstance(value, int):
        return enum(value)
    for policy, name in names.items():
        if name == value:
            return policy
    raise ValueError(f'{key}: {value!r} is not one of {", ".join(names.values())}')


def _parse_duration(value) -> Duration:
    if not isinstance(value, dict):
        raise ValueError(f'a duration must be a mapping with sec and nsec, got {value!r}')
    return Duration(seconds=int(value.get('sec', 0)), nanoseconds=int(value.get('nsec', 0)))


def qos_from_dict(entry: dict) -> QoSProfile:
    """A profile from rosbag2's YAML form (names, or the integers of metadata before v9).

    :raises ValueError: naming the bad key and value.
    """
    if not isinstance(entry, dict):
        raise ValueError(f'a QoS profile must be a mapping, got {entry!r}')
    history = _policy(entry.get('history', 'keep_last'), _HISTORY, HistoryPolicy, 'history')
    kwargs = {'history': history, 'depth': int(entry.get('depth', 10) or 10)}
    for key, names, enum in (('reliability', _RELIABILITY, ReliabilityPolicy),
                             ('durability', _DURABILITY, DurabilityPolicy),
                             ('liveliness', _LIVELINESS, LivelinessPolicy)):
        if key in entry:
            kwargs[key] = _policy(entry[key], names, enum, key)
    for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        if key in entry:
            kwargs[key] = _parse_duration(entry[key])
    if 'avoid_ros_namespace_conventions' in entry:
        kwargs['avoid_ros_namespace_conventions'] = bool(
            entry['avoid_ros_namespace_conventions'])
    return QoSProfile(**kwargs)


def qos_from_yaml(text: str) -> List[QoSProfile]:
    """Parse ``offered_qos_profiles`` channel metadata (empty text: no profiles)."""
    if not text.strip():
        return []
    entries = yaml.safe_load(text)
    if not isinstance(entries, list):
        raise ValueError(f'offered_qos_profiles must be a YAML list, got {text[:80]!r}')
    return [qos_from_dict(entry) for entry in entries]


# --- writing ------------------------------------------------------------------------------------

class _FileSink:
    """An output file: position tracking, small writes gathered, large ones passed through.

    The mcap Writer writes its records through :meth:`write`; :meth:`writev` writes a message
    record from several buffers (header, head, payload view, suffix) with one system call.
    :meth:`write_direct` writes page-aligned memory to a page-aligned file offset with
    ``O_DIRECT``: the disk reads it from where it is (a shared-memory frame), no copy into the
    page cache, almost no CPU. It is available where the file system supports ``O_DIRECT``.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        try:
            self._direct_fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC |
                                      getattr(os, 'O_DIRECT', 0)) if hasattr(os, 'O_DIRECT') \
                else -1
        except OSError:  # tmpfs and some others: no O_DIRECT
            self._direct_fd = -1
        self._position = 0
        self._flushed = 0  # file offset where the pending bytes go
        self._pending = bytearray()

    def tell(self) -> int:
        return self._position

    def write(self, data) -> int:
        return self.writev([data])

    def writev(self, buffers: Sequence) -> int:
        """Write ``buffers`` one after the other; small ones are gathered first."""
        views = [memoryview(b).cast('B') for b in buffers]
        total = sum(v.nbytes for v in views)
        if total < _SMALL_WRITE:
            for view in views:
                self._pending += view
            if len(self._pending) >= _SMALL_WRITE:
                self.flush()
        else:
            if self._pending:
                views.insert(0, memoryview(bytes(self._pending)))
                self._pending.clear()
            self._write_all(self._fd, views)
        self._position += total
        return total

    def direct_ok(self, view: memoryview) -> bool:
        """True when :meth:`write_direct` can take ``view`` (its address and size aligned)."""
        if self._direct_fd < 0 or view.nbytes < DIRECT_MIN_BYTES:
            return False
        import numpy
        address = numpy.frombuffer(view, dtype=numpy.uint8).ctypes.data
        return address % DIRECT_ALIGNMENT == 0

    def write_direct(self, view: memoryview) -> int:
        """Write the aligned prefix of ``view`` with O_DIRECT (the position must be aligned);
        return how many bytes were written (a multiple of the alignment)."""
        assert self._position % DIRECT_ALIGNMENT == 0
        self.flush()
        nbytes = view.nbytes - view.nbytes % DIRECT_ALIGNMENT
        done = 0
        try:
            while done < nbytes:
                written = os.pwrite(self._direct_fd, view[done:nbytes], self._position + done)
                if written <= 0 or written % DIRECT_ALIGNMENT:
                    done += max(written, 0)
                    break
                done += written
        except OSError:  # the file system refused after all: buffered from now on
            os.close(self._direct_fd)
            self._direct_fd = -1
        self._position += done
        self._flushed = self._position
        return done

    def _write_all(self, fd: int, views: List[memoryview]) -> None:
        while views:
            written = os.pwritev(fd, views[:_MAX_IOV], self._flushed)
            self._flushed += written
            while views and written >= views[0].nbytes:
                written -= views[0].nbytes
                views.pop(0)
            if views and written:
                views[0] = views[0][written:]

    def flush(self) -> None:
        if self._pending:
            data = bytes(self._pending)
            self._pending.clear()
            self._write_all(self._fd, [memoryview(data)])

    def fileno(self) -> int:
        return self._fd

    def sync(self) -> None:
        """Write what is pending and make it durable (fdatasync)."""
        self.flush()
        os.fdatasync(self._fd)

    def truncate(self, size: int) -> None:
        """Drop everything after ``size`` bytes (a write cut short: ENOSPC); pending bytes
        are dropped too."""
        self._pending.clear()
        os.ftruncate(self._fd, size)
        self._position = self._flushed = size

    def close(self) -> None:
        if self._fd >= 0:
            try:
                self.flush()
            finally:
                os.close(self._fd)
                self._fd = -1
                if self._direct_fd >= 0:
                    os.close(self._direct_fd)
                    self._direct_fd = -1


@dataclass
class Topic:
    """A recorded topic: what its channel says and what was written on it."""

    name: str
    type: str
    definition: MessageDefinition
    offered_qos: List[QoSProfile] = field(default_factory=list)
    type_hash: str = ''
    message_count: int = 0

    def channel_metadata(self) -> Dict[str, str]:
        return {'offered_qos_profiles': qos_to_yaml(self.offered_qos),
                'topic_type_hash': self.type_hash}

    def metadata_entry(self, message_count: int) -> dict:
        return {'topic_metadata': {
            'name': self.name, 'type': self.type, 'serialization_format': SERIALIZATION_FORMAT,
            'offered_qos_profiles': [p if isinstance(p, dict) else qos_to_dict(p)
                                     for p in self.offered_qos],
            'type_description_hash': self.type_hash},
            'message_count': message_count}


@dataclass
class _FileInfo:
    path: str
    message_count: int = 0
    start: Optional[int] = None
    end: Optional[int] = None
    topic_counts: Dict[str, int] = field(default_factory=dict)

    def add(self, topic: str, log_time: int) -> None:
        self.message_count += 1
        self.topic_counts[topic] = self.topic_counts.get(topic, 0) + 1
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)


def _time_range(files) -> Tuple[int, int]:
    starts = [f.start for f in files if f.start is not None]
    ends = [f.end for f in files if f.end is not None]
    if not starts:
        return 0, 0
    return min(starts), max(ends) - min(starts)


def bag_metadata(topics: Sequence[Topic], files: Sequence[_FileInfo],
                 topic_counts: Dict[str, int]) -> dict:
    """rosbag2's ``metadata.yaml`` content (``BagMetadata``, version 9)."""
    start, duration = _time_range(files)
    return {'rosbag2_bagfile_information': {
        'version': METADATA_VERSION,
        'storage_identifier': STORAGE_ID,
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': sum(f.message_count for f in files),
        'topics_with_message_count': [t.metadata_entry(topic_counts.get(t.name, 0))
                                      for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path,
                   'starting_time': {'nanoseconds_since_epoch': f.start or 0},
                   'duration': {'nanoseconds': (f.end or 0) - (f.start or 0)},
                   'message_count': f.message_count} for f in files],
        'custom_data': {},
        'ros_distro': os.environ.get('ROS_DISTRO', 'jazzy'),
    }}


def write_metadata_yaml(directory: Path, metadata: dict) -> None:
    """Write ``directory/metadata.yaml`` atomically: a temporary file, fsync, rename, fsync of
    the directory. A crash or a full disk leaves the previous state (no file), never an empty
    or partial one.

    :raises BagError: naming the file and the system error (the temporary file is removed).
    """
    target = Path(directory) / 'metadata.yaml'
    temporary = target.with_name(f'.metadata.yaml.{os.getpid()}.tmp')
    data = yaml.safe_dump(metadata, sort_keys=False).encode('utf-8')
    try:
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.rename(temporary, target)
        directory_fd = os.open(target.parent, os.O_RDONLY | os.O_CLOEXEC)
        try:
            os.fsync(directory_fd)
        finally:
            os.close(directory_fd)
    except OSError as exc:
        try:
            temporary.unlink()
        except OSError:
            pass
        raise BagError(f'{target}: cannot write: {exc.strerror or exc}') from None


class _LibraryState:
    """The mcap 1.x Writer's statistics and chunk indexes, which this module fills in for the
    chunks it writes itself: the one place that reaches into the library's private state."""

    def __init__(self, writer: Writer) -> None:
        self.statistics = getattr(writer, '_Writer__statistics', None)
        self.chunk_indexes = getattr(writer, '_Writer__chunk_indices', None)
        if not hasattr(self.statistics, 'channel_message_counts') or \
                not isinstance(self.chunk_indexes, list):
            raise BagError('this version of the mcap library keeps its writer state elsewhere; '
                           'rosidl_buffer_py needs mcap 1.x')

    def add_chunk(self, index: ChunkIndex, counts: Dict[int, int]) -> None:
        stats = self.statistics
        stats.message_start_time = index.message_start_time if stats.message_count == 0 \
            else min(stats.message_start_time, index.message_start_time)
        stats.message_end_time = max(stats.message_end_time, index.message_end_time)
        for channel_id, count in counts.items():
            stats.channel_message_counts[channel_id] += count
            stats.message_count += count
        stats.chunk_count += 1
        self.chunk_indexes.append(index)


class _Syncer:
    """``fdatasync`` of the file being written, in a thread of its own, so that the thread that
    writes never waits for the disk (syncing a second of a buffered 4K stream can take that
    long, and the recorder's queue would overflow meanwhile).
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._fd: Optional[int] = None   # a file to sync, requested and not started yet
        self._busy = False
        self._closed = False
        self.error: Optional[OSError] = None  #: the last failure, for the writer to raise
        self._thread = threading.Thread(target=self._run, name='bag_sync', daemon=True)
        self._thread.start()

    def request(self, fd: int) -> None:
        with self._condition:
            self._fd = fd
            self._condition.notify_all()

    def quiesce(self) -> None:
        """Forget a pending request and wait for a running sync: ``fd`` may be closed after."""
        with self._condition:
            self._fd = None
            while self._busy:
                self._condition.wait()

    def close(self) -> None:
        self.quiesce()
        with self._condition:
            self._closed = True
            self._condition.notify_all()
        self._thread.join()

    def _run(self) -> None:
        while True:
            with self._condition:
                while self._fd is None and not self._closed:
                    self._condition.wait()
                if self._closed:
                    return
                fd, self._fd, self._busy = self._fd, None, True
            try:
                os.fdatasync(fd)
            except OSError as exc:
                self.error = exc
            finally:
                with self._condition:
                    self._busy = False
                    self._condition.notify_all()


class _PendingChunk:
    """Records of small messages gathered into the next chunk (copied: a few KiB each, so that
    no shared-memory frame is held while the chunk fills)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.entries: List[Tuple[str, int, int, int]] = []  # topic, channel id, log time, offset
        self.opened = 0.0  # time.monotonic() of its first message
        self.nbytes = 0    # message data (CDR) bytes

    def add(self, topic: str, channel_id: int, log_time: int, parts: Sequence,
            nbytes: int) -> None:
        if not self.entries:
            self.opened = time.monotonic()
        self.entries.append((topic, channel_id, log_time, len(self.data)))
        for part in parts:
            self.data += part
        self.nbytes += nbytes

    def clear(self) -> None:
        self.data = bytearray()
        self.entries = []
        self.nbytes = 0


def chunk_header(start: int, end: int, size: int, crc: int = 0) -> bytes:
    """The bytes of an uncompressed chunk record before its ``size`` bytes of records."""
    return _CHUNK_HEADER.pack(Opcode.CHUNK, _CHUNK_FIXED + size, start, end, size, crc, 0, size)


def message_indexes(entries: Sequence[Tuple[int, int, int]]) -> Dict[int, bytes]:
    """Message index records of a chunk from its (channel id, log time, offset) entries:
    channel id -> the record's bytes."""
    per_channel: Dict[int, List[Tuple[int, int]]] = {}
    for channel_id, log_time, offset in entries:
        per_channel.setdefault(channel_id, []).append((log_time, offset))
    records = {}
    for channel_id, items in per_channel.items():
        builder = RecordBuilder()
        MessageIndex(channel_id, items).write(builder)
        records[channel_id] = bytes(builder.end())
    return records


class BagWriter:
    """Write a bag directory: topics, messages, splits, metadata.

    Thread-safe: the recorder adds topics from its executor while its writer thread writes.
    Call :meth:`tick` at least every :data:`FLUSH_PERIOD_SEC` (the recorder's writer thread
    does): it writes a chunk that has waited that long and fdatasyncs the file.

    :param directory: The bag directory; it must not exist yet (as with ``ros2 bag record``).
    :param max_bag_size: Start a new file before a message once the current file holds at
        least this many bytes (0: never).
    :param max_bag_duration_ns: Start a new file before a message logged this long after the
        current file's first message (0: never).
    """

    def __init__(self, directory: Path, *, max_bag_size: int = 0,
                 max_bag_duration_ns: int = 0, library: str = 'rosidl_buffer_py',
                 chunk_size: int = CHUNK_SIZE) -> None:
        self.directory = Path(directory)
        if self.directory.exists():
            raise BagError(f'{self.directory}: output already exists; choose another -o/--output')
        try:
            self.directory.mkdir(parents=True)
        except OSError as exc:
            raise BagError(f'{self.directory}: cannot create the bag directory: '
                           f'{exc.strerror}') from None
        self.max_bag_size = max_bag_size
        self.max_bag_duration_ns = max_bag_duration_ns
        self.chunk_size = chunk_size
        self.library = library
        self.topics: Dict[str, Topic] = {}
        self.files: List[_FileInfo] = []
        self.topic_counts: Dict[str, int] = {}  # messages in written chunks, all files
        self.bytes_written = 0  # message data bytes (CDR) in written chunks, all files
        self._sink: Optional[_FileSink] = None
        self._writer: Optional[Writer] = None
        self._library: Optional[_LibraryState] = None
        self._channels: Dict[str, int] = {}
        self._schemas: Dict[str, int] = {}
        self._sequences: Dict[str, int] = {}
        self._pending = _PendingChunk()
        self._good_end = 0     # file offset after the last record written completely
        self._last_sync = time.monotonic()
        self._unsynced = False
        self._syncer = _Syncer()
        self.failed = False  #: set by the caller when a write failed (see close)
        self._lock = threading.Lock()
        self._open_next()

    @property
    def file_paths(self) -> List[Path]:
        return [self.directory / f.path for f in self.files]

    def _open_next(self) -> None:
        info = _FileInfo(f'{self.directory.name}_{len(self.files)}.mcap')
        self._sink = _FileSink(self.directory / info.path)
        self._writer = Writer(self._sink, compression=CompressionType.NONE, use_chunking=False)
        self._library = _LibraryState(self._writer)
        self._writer.start(profile=PROFILE, library=self.library)
        self._channels.clear()
        self._schemas.clear()
        self._sequences.clear()
        self.files.append(info)
        for topic in self.topics.values():
            self._register(topic)
        self._writer.flush()
        self._good_end = self._sink.tell()

    def _register(self, topic: Topic) -> None:
        schema_id = self._schemas.get(topic.type)
        if schema_id is None:
            schema_id = self._writer.register_schema(
                topic.type, topic.definition.encoding, topic.definition.text.encode('utf-8'))
            self._schemas[topic.type] = schema_id
        self._channels[topic.name] = self._writer.register_channel(
            topic.name, SERIALIZATION_FORMAT, schema_id, topic.channel_metadata())

    def add_topic(self, topic: Topic) -> None:
        """Declare a topic (once): its schema and channel go into every file from now on."""
        with self._lock:
            if topic.name in self.topics:
                raise BagError(f'topic {topic.name} was already added')
            self.topics[topic.name] = topic
            self._write_pending()  # the channel record goes between chunks, never inside one
            self._register(topic)
            # unchunked, the library keeps these records until its next write: they must
            # precede the channel's messages, which are written here
            self._writer.flush()
            self._good_end = self._sink.tell()

    def _should_split(self, log_time: int) -> bool:
        current = self.files[-1]
        start = current.start if current.start is not None else (
            self._pending.entries[0][2] if self._pending.entries else None)
        if start is None:
            return False
        if self.max_bag_size and self._sink.tell() + len(self._pending.data) >= \
                self.max_bag_size:
            return True
        return bool(self.max_bag_duration_ns and log_time - start >= self.max_bag_duration_ns)

    def write(self, topic: str, log_time: int, publish_time: int, parts: Sequence) -> int:
        """Write one message; ``parts`` are bytes-like pieces of its CDR, written in order.

        A message smaller than the chunk size waits (copied) in the chunk being gathered; a
        larger one is written now, without a copy. Either way the message is on disk within
        :data:`FLUSH_PERIOD_SEC` (given :meth:`tick`).

        :return: The message's size in bytes.
        """
        with self._lock:
            return self._write(topic, log_time, publish_time, parts)

    def _write(self, topic: str, log_time: int, publish_time: int, parts: Sequence) -> int:
        if self._should_split(log_time):
            self._write_pending()
            self._finish_file()
            self._open_next()
        channel_id = self._channels[topic]
        size = sum(memoryview(p).nbytes for p in parts)
        sequence = self._sequences.get(topic, 0) + 1
        self._sequences[topic] = sequence
        header = _MESSAGE_HEADER.pack(Opcode.MESSAGE, _MESSAGE_FIXED + size, channel_id,
                                      sequence & 0xFFFFFFFF, log_time, publish_time)
        if size + len(header) < self.chunk_size:
            self._pending.add(topic, channel_id, log_time, [header, *parts], size)
            if len(self._pending.data) >= self.chunk_size:
                self._write_pending()
            return size
        self._write_pending()
        self._write_large(topic, channel_id, log_time, header, parts, size)
        return size

    def _write_pending(self) -> None:
        """Write the gathered chunk and its message indexes."""
        pending = self._pending
        if not pending.entries:
            return
        times = [entry[2] for entry in pending.entries]
        data = pending.data
        header = chunk_header(min(times), max(times), len(data), zlib.crc32(data))
        indexes = message_indexes([(c, t, o) for _, c, t, o in pending.entries])
        start = self._sink.tell()
        self._sink.writev([header, data])
        self._commit(start, len(header) + len(data), indexes, pending.entries, pending.nbytes)
        pending.clear()

    def _write_large(self, topic: str, channel_id: int, log_time: int, header: bytes,
                     parts: Sequence, size: int) -> None:
        """One message as a chunk of its own, the payload passed from where it is."""
        record = len(header) + size
        chunk = chunk_header(log_time, log_time, record)
        indexes = message_indexes([(channel_id, log_time, 0)])
        payload = memoryview(parts[1]).cast('B') if len(parts) == 3 else None
        if payload is not None and self._sink.direct_ok(payload):
            before = len(chunk) + len(header) + memoryview(parts[0]).nbytes
            pad = -(self._sink.tell() + _RECORD_PREFIX.size + before) % DIRECT_ALIGNMENT
            self._sink.writev([_RECORD_PREFIX.pack(PADDING_OPCODE, pad), bytes(pad)])
            start = self._sink.tell()
            self._sink.writev([chunk, header, parts[0]])
            done = self._sink.write_direct(payload)
            self._sink.writev([payload[done:], parts[2]])
        else:
            start = self._sink.tell()
            self._sink.writev([chunk, header, *parts])
        self._commit(start, len(chunk) + record, indexes, [(topic, channel_id, log_time, 0)],
                     size)

    def _commit(self, start: int, length: int, indexes: Dict[int, bytes],
                entries: Sequence[Tuple[str, int, int, int]], nbytes: int) -> None:
        """After a chunk: its message indexes, then the writer's statistics and chunk index."""
        index_start = self._sink.tell()
        offsets, position = {}, index_start
        for channel_id, record in indexes.items():
            offsets[channel_id] = position
            position += len(record)
        self._sink.writev(list(indexes.values()))
        self._sink.flush()
        times = [entry[2] for entry in entries]
        counts: Dict[int, int] = {}
        for topic, channel_id, log_time, _ in entries:
            counts[channel_id] = counts.get(channel_id, 0) + 1
            self.files[-1].add(topic, log_time)
            self.topic_counts[topic] = self.topic_counts.get(topic, 0) + 1
        self._library.add_chunk(ChunkIndex(
            message_start_time=min(times), message_end_time=max(times),
            chunk_start_offset=start, chunk_length=length, message_index_offsets=offsets,
            message_index_length=position - index_start, compression='',
            compressed_size=length - _CHUNK_HEADER.size,
            uncompressed_size=length - _CHUNK_HEADER.size), counts)
        self.bytes_written += nbytes
        self._good_end = self._sink.tell()
        self._unsynced = True

    def tick(self) -> None:
        """Write the gathered chunk once it is :data:`FLUSH_PERIOD_SEC` old, and have the file
        fdatasync'ed (by another thread) at most that often.

        :raises OSError: the last fdatasync failed (a disk error).
        """
        with self._lock:
            if self._sink is None:
                return
            if self._syncer.error is not None:
                error, self._syncer.error = self._syncer.error, None
                raise error
            now = time.monotonic()
            if self._pending.entries and now - self._pending.opened >= FLUSH_PERIOD_SEC:
                self._write_pending()
            if self._unsynced and now - self._last_sync >= FLUSH_PERIOD_SEC:
                self._sink.flush()
                self._syncer.request(self._sink.fileno())
                self._last_sync = now
                self._unsynced = False

    def _finish_file(self) -> None:
        current = self.files[-1]
        metadata = bag_metadata(list(self.topics.values()), [current], current.topic_counts)
        metadata['rosbag2_bagfile_information']['relative_file_paths'] = [self.files[-1].path]
        self._writer.add_metadata('rosbag2', {
            'serialized_metadata': yaml.safe_dump(metadata, sort_keys=False),
            'ROS_DISTRO': os.environ.get('ROS_DISTRO', 'jazzy')})
        self._writer.finish()
        self._syncer.quiesce()  # the file is synced here, then closed
        self._sink.sync()
        self._sink.close()

    def close(self, failed: bool = False) -> None:
        """Finish the current file and write ``metadata.yaml`` (atomically).

        :param failed: A write failed (a full disk): drop the record it cut short and finish
            the file after the last complete chunk; the summary and footer are small.
        :raises BagError: when the file cannot be finished; ``buffer_bag_reindex`` finishes it
            later (no metadata.yaml is written then).
        """
        with self._lock:
            if self._sink is None:
                return
            try:
                if failed:
                    self._pending.clear()
                    self._sink.truncate(self._good_end)
                else:
                    self._write_pending()
                self._finish_file()
            except OSError as exc:
                raise BagError(
                    f'{self.directory / self.files[-1].path}: cannot finish the file '
                    f'({exc.strerror or exc}); once there is room, run: buffer_bag_reindex '
                    f'{self.directory}') from None
            finally:
                sink, self._sink = self._sink, None
                self._syncer.close()
                if sink._fd >= 0:
                    sink._pending.clear()
                    sink.close()
            write_metadata_yaml(self.directory, bag_metadata(
                list(self.topics.values()), self.files, self.topic_counts))

    @property
    def size(self) -> int:
        """Bytes in all files so far."""
        if self._sink is None:
            return sum((self.directory / f.path).stat().st_size for f in self.files)
        done = sum((self.directory / f.path).stat().st_size for f in self.files[:-1])
        return done + self._sink.tell()


# --- reading ------------------------------------------------------------------------------------

class BagFile(NamedTuple):
    path: Path
    size: int
    summary: Summary
    metadata: dict   # the rosbag2 metadata record, parsed ({} when absent)


def bag_files(path: Path) -> List[Path]:
    """The MCAP files of a bag: a directory's (in split order, or as metadata.yaml lists them),
    or one file.

    :raises BagError: for a missing path or a directory without MCAP files.
    """
    path = Path(path)
    if path.is_dir():
        metadata = path / 'metadata.yaml'
        files = []
        if metadata.is_file():
            try:
                info = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
                files = [path / name for name in info.get('relative_file_paths', [])]
            except (yaml.YAMLError, KeyError, TypeError) as exc:
                raise BagError(f'{metadata}: not a rosbag2 metadata file ({exc})') from None
            missing = [str(f) for f in files if not f.is_file()]
            if missing:
                raise BagError(f'{path}: metadata.yaml lists missing files: {", ".join(missing)}')
        if not files:
            def split_index(p: Path):
                stem = p.stem.rsplit('_', 1)
                return (int(stem[1]) if len(stem) == 2 and stem[1].isdigit() else -1, p.name)
            files = sorted(path.glob('*.mcap'), key=split_index)
        if not files:
            raise BagError(f'{path}: no .mcap files in this directory')
        return files
    if path.is_file():
        return [path]
    raise BagError(f'{path}: no such file or directory')


def _open_file(path: Path) -> BagFile:
    try:
        size = path.stat().st_size
        with open(path, 'rb') as stream:
            if stream.read(len(MCAP0_MAGIC)) != MCAP0_MAGIC:
                raise BagError(f'{path}: not an MCAP file (it does not start with the MCAP magic)')
            stream.seek(max(0, size - len(MCAP0_MAGIC)))
            if size < 2 * len(MCAP0_MAGIC) or stream.read() != MCAP0_MAGIC:
                raise BagError(f'{path}: truncated MCAP file ({size} bytes, no footer: its '
                               'writer did not finish it); recover its messages with: '
                               f'buffer_bag_reindex {path.parent}')
            stream.seek(0)
            reader = make_reader(stream)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                raise BagError(f'{path}: the MCAP file has no summary statistics (not written '
                               'by a recorder that finished it)')
            metadata = {}
            for record in reader.iter_metadata():
                if record.name == 'rosbag2':
                    metadata = dict(record.metadata)
    except BagError:
        raise
    except OSError as exc:
        raise BagError(f'{path}: cannot read: {exc.strerror or exc}') from None
    except (McapError, EOFError, struct.error, ValueError, KeyError, IndexError,
            UnicodeDecodeError) as exc:
        raise BagError(f'{path}: not a complete MCAP file (truncated or damaged: '
                       f'{type(exc).__name__}: {exc})') from None
    return BagFile(path, size, summary, metadata)


class BagReader:
    """A recorded bag (directory or single file): its files' summaries and their messages.

    :raises BagError: when a file is missing, truncated or not MCAP.
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        self.files = [_open_file(p) for p in bag_files(self.path)]
        self.topics: Dict[str, dict] = {}
        for bag_file in self.files:
            summary = bag_file.summary
            counts = summary.statistics.channel_message_counts
            for channel_id, channel in summary.channels.items():
                schema = summary.schemas.get(channel.schema_id)
                entry = self.topics.setdefault(channel.topic, {
                    'name': channel.topic, 'type': schema.name if schema else '',
                    'serialization_format': channel.message_encoding,
                    'offered_qos_profiles': channel.metadata.get('offered_qos_profiles', ''),
                    'type_hash': channel.metadata.get('topic_type_hash', ''),
                    'count': 0})
                entry['count'] += counts.get(channel_id, 0)

    @property
    def ros_distro(self) -> str:
        """The ROS distribution the bag was recorded with ('' when it does not say): from a
        file's ``rosbag2`` metadata record (its ``ROS_DISTRO`` key, or ``ros_distro`` in the
        ``serialized_metadata`` rosbag2 embeds), else from the directory's metadata.yaml."""
        for bag_file in self.files:
            if bag_file.metadata.get('ROS_DISTRO'):
                return bag_file.metadata['ROS_DISTRO']
            distro = _info_field(bag_file.metadata.get('serialized_metadata', ''), 'ros_distro')
            if distro:
                return distro
        metadata = self.path / 'metadata.yaml'
        if self.path.is_dir() and metadata.is_file():
            try:
                return _info_field(metadata.read_text(), 'ros_distro')
            except OSError:
                pass
        return ''

    @property
    def message_count(self) -> int:
        return sum(f.summary.statistics.message_count for f in self.files)

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    def time_range(self) -> Tuple[int, int]:
        """(first, last) log time in ns; (0, 0) for a bag without messages."""
        stats = [f.summary.statistics for f in self.files if f.summary.statistics.message_count]
        if not stats:
            return 0, 0
        return (min(s.message_start_time for s in stats),
                max(s.message_end_time for s in stats))

    def messages(self, topics: Optional[Sequence[str]] = None
                 ) -> Iterator[Tuple[Channel, Message]]:
        """Every message of the selected topics in log-time order, whatever the file order.

        Memory stays bounded: each file is read through its chunk indexes (mcap's reader keeps
        only the chunks whose time ranges overlap), and the files are merged by log time. A file
        without chunk indexes (this package's recorder before it wrote chunks) is read in file
        order, which is recording order.
        """
        streams = [self._file_messages(bag_file, topics) for bag_file in self.files]
        yield from heapq.merge(*streams, key=lambda item: item[1].log_time)

    def _file_messages(self, bag_file: BagFile, topics: Optional[Sequence[str]]
                       ) -> Iterator[Tuple[Channel, Message]]:
        indexed = bool(bag_file.summary.chunk_indexes)
        try:
            with open(bag_file.path, 'rb') as stream:
                reader = make_reader(stream)
                for _, channel, message in reader.iter_messages(
                        topics=topics, log_time_order=indexed):
                    yield channel, message
        except (McapError, EOFError, struct.error) as exc:
            raise BagError(f'{bag_file.path}: damaged message data '
                           f'({type(exc).__name__}: {exc})') from None


def _info_field(text: str, key: str) -> str:
    """``rosbag2_bagfile_information[key]`` of rosbag2 metadata YAML ('' if absent or not
    YAML)."""
    if not text:
        return ''
    try:
        info = yaml.safe_load(text)['rosbag2_bagfile_information']
    except (yaml.YAMLError, KeyError, TypeError):
        return ''
    value = info.get(key) if isinstance(info, dict) else None
    return str(value) if value else ''


def format_size(nbytes: float) -> str:
    """``ros2 bag info``'s size format (B, KiB, MiB, GiB)."""
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if nbytes < 1024 or unit == 'GiB':
            return f'{nbytes:.1f} {unit}' if unit != 'B' else f'{int(nbytes)} B'
        nbytes /= 1024
    return f'{nbytes} B'

