"""buffer_bag_reindex: finish the MCAP files of a bag that was cut short, as ``ros2 bag reindex``.

A recorder killed (SIGKILL, a crash, power loss) or stopped by a full disk leaves its last file
without summary and footer, and the bag without ``metadata.yaml``: readers refuse it. This
command scans each such file record by record, keeps every complete record, and finishes the
file in place: it cuts the file after the last complete chunk (with its message indexes),
appends the complete messages of a chunk the cut went through as a new chunk, then the summary
(schemas, channels, statistics, chunk and metadata indexes) and the footer. Cutting first frees
what the damaged tail held, so a bag stopped by a full disk can be finished on that same disk.
Then ``metadata.yaml`` is written (atomically) for the whole bag. Files that are complete are
only read.

Usage: ``buffer_bag_reindex <bag>``; also ``python -m rosidl_buffer_py.tools.reindex``.
"""
import argparse
import io
import os
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import yaml

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, Metadata, MetadataIndex, Schema, Statistics,
    SummaryOffset)
from mcap.stream_reader import breakup_chunk
from mcap.writer import MCAP0_MAGIC

from rosidl_buffer_py.tools.bag import (
    BagError, Topic, bag_metadata, chunk_header, message_indexes,
    write_metadata_yaml, _FileInfo)

__all__ = ['FileRepair', 'main', 'reindex_bag', 'reindex_file']

EXIT_USAGE = 2
_PREFIX = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel id, sequence, log time, publish time
_CHUNK_FIXED = struct.Struct('<QQQI')  # start, end, uncompressed size, uncompressed crc


@dataclass
class FileRepair:
    """What reindexing did to one file."""

    path: Path
    complete: bool              #: it already had its summary and footer (nothing changed)
    messages: int = 0           #: messages in the file afterwards
    recovered: int = 0          #: of those, messages rescued from a chunk the cut went through
    dropped_bytes: int = 0      #: bytes of the damaged tail removed
    topic_counts: Dict[str, int] = field(default_factory=dict)
    start: Optional[int] = None
    end: Optional[int] = None


@dataclass
class _Scan:
    """The records of a file up to the first incomplete one."""

    schemas: Dict[int, Schema] = field(default_factory=dict)
    channels: Dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: List[ChunkIndex] = field(default_factory=list)
    metadata_indexes: List[MetadataIndex] = field(default_factory=list)
    counts: Dict[int, int] = field(default_factory=dict)
    start: Optional[int] = None
    end: Optional[int] = None
    chunk_count: int = 0
    attachment_count: int = 0
    cut: int = 0               #: the file is kept up to here
    complete: bool = False     #: a DataEnd record was found: the file has its summary
    rescued: List[Tuple[int, int, bytes]] = field(default_factory=list)  # channel, time, record

    def count(self, channel_id: int, log_time: int) -> None:
        self.counts[channel_id] = self.counts.get(channel_id, 0) + 1
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)


def _messages_in(records: bytes) -> List[Tuple[int, int, int, int]]:
    """(channel id, log time, offset, length) of each complete message record in ``records``
    (a chunk's uncompressed data, perhaps cut short)."""
    found, offset, size = [], 0, len(records)
    while offset + _PREFIX.size <= size:
        opcode, length = _PREFIX.unpack_from(records, offset)
        end = offset + _PREFIX.size + length
        if end > size:
            break
        if opcode == Opcode.MESSAGE and length >= _MESSAGE_HEAD.size:
            channel_id, _, log_time, _ = _MESSAGE_HEAD.unpack_from(records, offset + _PREFIX.size)
            found.append((channel_id, log_time, offset, end - offset))
        offset = end
    return found


def _parse(record_type, body: bytes):
    return record_type.read(ReadDataStream(io.BytesIO(body)))


@dataclass
class _OpenChunk:
    """A complete chunk whose message indexes are being read."""

    start: int
    index: ChunkIndex
    messages: List[Tuple[int, int, int, int]]
    records: bytes
    missing: set

    def rescue(self, scan: '_Scan') -> None:
        """Its messages, to be written again as a new chunk (its indexes were cut)."""
        for channel_id, log_time, offset, length in self.messages:
            scan.rescued.append((channel_id, log_time, self.records[offset:offset + length]))

    def accept(self, scan: '_Scan') -> None:
        for channel_id, log_time, _, _ in self.messages:
            scan.count(channel_id, log_time)
        scan.chunk_indexes.append(self.index)
        scan.chunk_count += 1


def _chunk_records(chunk: Chunk) -> bytes:
    """A chunk's uncompressed records (mcap's own decompression for lz4 / zstd)."""
    if not chunk.compression:
        return chunk.data
    builder = RecordBuilder()
    for record in breakup_chunk(chunk):
        record.write(builder)
    return bytes(builder.end())


#: Top-level records whose body the scan reads (others are skipped by their length).
_READ_BODY = {Opcode.CHUNK, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA}


def _scan(path: Path) -> _Scan:
    """Walk the top-level records of ``path``; stop at the first one cut short."""
    scan = _Scan()
    size = path.stat().st_size
    with open(path, 'rb') as stream:
        if stream.read(len(MCAP0_MAGIC)) != MCAP0_MAGIC:
            raise BagError(f'{path}: not an MCAP file (it does not start with the MCAP magic)')
        offset = scan.cut = len(MCAP0_MAGIC)
        open_chunk: Optional[_OpenChunk] = None
        while True:
            if offset + _PREFIX.size > size:
                break
            stream.seek(offset)
            opcode, length = _PREFIX.unpack(stream.read(_PREFIX.size))
            end = offset + _PREFIX.size + length
            if end > size:
                if opcode == Opcode.CHUNK:
                    _rescue_cut_chunk(stream, offset, size, scan)
                break
            if opcode == Opcode.MESSAGE_INDEX and open_chunk is not None:
                channel_id = struct.unpack('<H', stream.read(2))[0]
                index = open_chunk.index
                index.message_index_offsets[channel_id] = offset
                index.message_index_length = end - (index.chunk_start_offset +
                                                    index.chunk_length)
                open_chunk.missing.discard(channel_id)
                if not open_chunk.missing:
                    open_chunk.accept(scan)
                    open_chunk = None
                    scan.cut = end
                offset = end
                continue
            if open_chunk is not None:  # a complete record follows: indexes were not written
                open_chunk.accept(scan)
                open_chunk = None
            if opcode == Opcode.DATA_END:
                # complete only if the summary after it is: the file ends with the magic
                stream.seek(size - len(MCAP0_MAGIC))
                scan.complete = stream.read() == MCAP0_MAGIC
                scan.cut = offset  # else the summary is written again from here
                break
            body = stream.read(length) if opcode in _READ_BODY else b''
            if opcode == Opcode.CHUNK:
                chunk = _parse(Chunk, body)
                records = _chunk_records(chunk)
                messages = _messages_in(records)
                if messages:
                    open_chunk = _OpenChunk(offset, ChunkIndex(
                        message_start_time=chunk.message_start_time,
                        message_end_time=chunk.message_end_time, chunk_start_offset=offset,
                        chunk_length=end - offset, message_index_offsets={},
                        message_index_length=0, compression=chunk.compression,
                        compressed_size=len(chunk.data),
                        uncompressed_size=chunk.uncompressed_size),
                        messages, records, {m[0] for m in messages})
                    offset = end  # cut stays before it until its indexes are read
                    continue
            elif opcode == Opcode.SCHEMA:
                schema = _parse(Schema, body)
                scan.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                channel = _parse(Channel, body)
                scan.channels[channel.id] = channel
            elif opcode == Opcode.MESSAGE:
                channel_id, _, log_time, _ = _MESSAGE_HEAD.unpack_from(body)
                scan.count(channel_id, log_time)
            elif opcode == Opcode.METADATA:
                scan.metadata_indexes.append(
                    MetadataIndex(offset, end - offset, _parse(Metadata, body).name))
            elif opcode == Opcode.ATTACHMENT:
                scan.attachment_count += 1
            scan.cut = offset = end
        if open_chunk is not None:  # cut among its message indexes: write it again
            open_chunk.rescue(scan)
            scan.cut = open_chunk.start
    return scan


def _rescue_cut_chunk(stream, offset: int, size: int, scan: _Scan) -> None:
    """The complete messages of an uncompressed chunk the file ends in."""
    stream.seek(offset + _PREFIX.size + _CHUNK_FIXED.size)
    head = stream.read(4)
    if len(head) < 4:
        return
    compression_length = struct.unpack('<I', head)[0]
    if compression_length:  # compressed: nothing can be read from a part of it
        return
    stream.seek(8, os.SEEK_CUR)  # compressed size
    records = stream.read(max(0, size - stream.tell()))
    messages = _messages_in(records)
    for channel_id, log_time, start, length in messages:
        scan.rescued.append((channel_id, log_time, records[start:start + length]))


def _write_summary(stream, scan: _Scan) -> None:
    """DataEnd, the summary section and the footer, as mcap's Writer.finish writes them."""
    builder = RecordBuilder()
    DataEnd(0).write(builder)
    stream.write(builder.end())
    summary_start = stream.tell()
    summary = RecordBuilder()
    offsets = []

    def group(opcode: int, records) -> None:
        records = list(records)
        if not records:
            return
        start = summary.count
        for record in records:
            record.write(summary)
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                     group_length=summary.count - start))

    group(Opcode.SCHEMA, scan.schemas.values())
    group(Opcode.CHANNEL, scan.channels.values())
    group(Opcode.STATISTICS, [Statistics(
        attachment_count=scan.attachment_count, channel_count=len(scan.channels),
        channel_message_counts=dict(scan.counts), chunk_count=scan.chunk_count,
        message_count=sum(scan.counts.values()),
        message_end_time=scan.end or 0, message_start_time=scan.start or 0,
        metadata_count=len(scan.metadata_indexes), schema_count=len(scan.schemas))])
    group(Opcode.CHUNK_INDEX, scan.chunk_indexes)
    group(Opcode.METADATA_INDEX, scan.metadata_indexes)
    offset_start = summary_start + summary.count
    for offset in offsets:
        offset.write(summary)
    Footer(summary_start=summary_start, summary_offset_start=offset_start,
           summary_crc=0).write(summary)
    stream.write(summary.end())
    stream.write(MCAP0_MAGIC)


def _write_rescued(stream, scan: _Scan) -> None:
    """The rescued messages as one new chunk, with its message indexes."""
    if not scan.rescued:
        return
    records = b''.join(record for _, _, record in scan.rescued)
    entries, offset = [], 0
    for channel_id, log_time, record in scan.rescued:
        entries.append((channel_id, log_time, offset))
        offset += len(record)
    times = [t for _, t, _ in scan.rescued]
    start = stream.tell()
    header = chunk_header(min(times), max(times), len(records), zlib.crc32(records))
    stream.write(header)
    stream.write(records)
    index_start = stream.tell()
    index_offsets = {}
    for channel_id, record in message_indexes(entries).items():
        index_offsets[channel_id] = stream.tell()
        stream.write(record)
    scan.chunk_indexes.append(ChunkIndex(
        message_start_time=min(times), message_end_time=max(times), chunk_start_offset=start,
        chunk_length=len(header) + len(records), message_index_offsets=index_offsets,
        message_index_length=stream.tell() - index_start, compression='',
        compressed_size=len(records), uncompressed_size=len(records)))
    scan.chunk_count += 1
    for channel_id, log_time, _ in scan.rescued:
        scan.count(channel_id, log_time)


def reindex_file(path: Path) -> Tuple[FileRepair, _Scan]:
    """Finish ``path`` in place if it lacks its summary; report what it holds.

    :raises BagError: for a file that is not MCAP, or that cannot be written.
    """
    path = Path(path)
    try:
        scan = _scan(path)
        size = path.stat().st_size
        repair = FileRepair(path, complete=scan.complete)
        if not scan.complete:
            repair.recovered = len(scan.rescued)
            repair.dropped_bytes = size - scan.cut
            with open(path, 'r+b') as stream:
                stream.truncate(scan.cut)  # first: frees the damaged tail's space
                stream.seek(scan.cut)
                _write_rescued(stream, scan)
                _write_summary(stream, scan)
                stream.flush()
                os.fsync(stream.fileno())
    except OSError as exc:
        raise BagError(f'{path}: cannot reindex: {exc.strerror or exc}') from None
    except (struct.error, ValueError, KeyError, UnicodeDecodeError) as exc:
        raise BagError(f'{path}: damaged beyond a cut tail ({type(exc).__name__}: {exc})') \
            from None
    topics = {cid: channel.topic for cid, channel in scan.channels.items()}
    repair.messages = sum(scan.counts.values())
    for channel_id, count in scan.counts.items():
        topic = topics.get(channel_id, f'channel {channel_id}')
        repair.topic_counts[topic] = repair.topic_counts.get(topic, 0) + count
    repair.start, repair.end = scan.start, scan.end
    return repair, scan


def _split_index(path: Path) -> Tuple[int, str]:
    stem = path.stem.rsplit('_', 1)
    return (int(stem[1]) if len(stem) == 2 and stem[1].isdigit() else -1, path.name)


def reindex_bag(directory: Path) -> List[FileRepair]:
    """Finish every cut file of the bag ``directory`` and write its ``metadata.yaml``.

    :raises BagError: for a directory without MCAP files, or one that cannot be written.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f'{directory}: not a bag directory (buffer_record -o DIR makes one)')
    paths = sorted(directory.glob('*.mcap'), key=_split_index)
    if not paths:
        raise BagError(f'{directory}: no .mcap files in this directory')
    repairs, topics = [], {}
    for path in paths:
        repair, scan = reindex_file(path)
        repairs.append(repair)
        for channel in scan.channels.values():
            if channel.topic in topics:
                continue
            schema = scan.schemas.get(channel.schema_id)
            # the channel's profiles as written (a round trip through QoSProfile could change
            # them, and readers match metadata.yaml with the channels)
            try:
                offered = yaml.safe_load(channel.metadata.get('offered_qos_profiles', '')) or []
            except yaml.YAMLError:
                offered = []
            topics[channel.topic] = Topic(channel.topic, schema.name if schema else '', None,
                                          offered, channel.metadata.get('topic_type_hash', ''))
    files = []
    counts: Dict[str, int] = {}
    for repair in repairs:
        info = _FileInfo(repair.path.name, repair.messages, repair.start, repair.end,
                         dict(repair.topic_counts))
        files.append(info)
        for topic, count in repair.topic_counts.items():
            counts[topic] = counts.get(topic, 0) + count
    metadata = bag_metadata(list(topics.values()), files, counts)
    write_metadata_yaml(directory, metadata)
    return repairs


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog='buffer_bag_reindex',
        description='Finish the MCAP files of a bag cut short by SIGKILL, a crash or a full '
                    'disk (every complete message is kept) and write its metadata.yaml.')
    parser.add_argument('bag', help='bag directory (as buffer_record -o made it)')
    args = parser.parse_args(argv)
    try:
        repairs = reindex_bag(Path(args.bag))
    except BagError as exc:
        print(f'buffer_bag_reindex: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    for repair in repairs:
        if repair.complete:
            print(f'{repair.path.name}: complete, {repair.messages} messages (unchanged)')
        else:
            print(f'{repair.path.name}: recovered {repair.messages} messages '
                  f'({repair.recovered} from a cut chunk; {repair.dropped_bytes} bytes of '
                  'incomplete data dropped)')
    total = sum(r.messages for r in repairs)
    fixed = sum(not r.complete for r in repairs)
    print(f'buffer_bag_reindex: {args.bag}: {total} messages in {len(repairs)} file'
          f'{"s" if len(repairs) != 1 else ""} ({fixed} finished); metadata.yaml written')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
