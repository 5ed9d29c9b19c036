"""The readable part of a damaged rosbag2 recording: cut short (power lost while recording), or
without ``metadata.yaml``.

rosbags refuses such recordings whole (an MCAP file without its footer: "File end magic is
invalid"; an SQLite file cut short: "database disk image is malformed"). Here every storage file
is streamed record by record up to the damage:

- MCAP: records after the header, unchunked or in chunks (uncompressed, lz4 or zstd as rosbags
  decompresses them), up to the first record that is cut off or malformed; topics and types from
  the Schema and Channel records, so no summary, footer or metadata.yaml is needed.
- SQLite 3: the ``topics`` table, then the ``messages`` table in row order up to the first page
  that cannot be read; the database is opened read-only (``writable_schema`` only relaxes the
  schema check, nothing is written).

:class:`SalvageReader` offers what :class:`~youbot_fdi.bag.reader.RecordingReader` uses of rosbags'
reader (connections with message counts, ``messages``, start time and duration) and says in
:attr:`SalvageReader.damage` what was lost.
"""
from dataclasses import dataclass
from pathlib import Path
import sqlite3
import struct

import yaml

from youbot_fdi.yamlio import load_yaml

MCAP_MAGIC = b'\x89MCAP0\r\n'
MCAP_SCHEMA, MCAP_CHANNEL, MCAP_MESSAGE, MCAP_CHUNK, MCAP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F
MCAP_RECORD_HEADER = 9  # opcode (1 byte) + record length (uint64)
MCAP_MESSAGE_HEADER = 22  # channel id u16, sequence u32, log time u64, publish time u64
MCAP_CHUNK_HEADER = 28  # start time u64, end time u64, uncompressed size u64, crc u32
STORAGE_SUFFIXES = {'.mcap': 'mcap', '.db3': 'sqlite3'}
NANOSECONDS = 1e9


class SalvageError(Exception):
    """Nothing of the recording can be read."""


@dataclass(frozen=True)
class Connection:
    """A topic as rosbags describes it (the fields the reader uses)."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


@dataclass(frozen=True)
class Damage:
    """What reading a recording without rosbags found: how far it could be read, and what is
    known of what was lost (metadata.yaml's counts, when it exists)."""

    files: tuple  # names of the storage files, in order
    reason: str  # why reading stopped ('' when everything was read)
    messages: int  # messages read (every topic)
    first_time: float  # [s] bag time of the first message read
    last_time: float  # [s] bag time of the last message read
    expected_messages: object  # int from metadata.yaml, or None
    expected_duration: object  # [s] from metadata.yaml, or None
    unreadable_bytes: object  # bytes left in the damaged file after the readable part (None: unknown)
    metadata_missing: bool

    @property
    def lost(self):
        """True when part of the recording could not be read."""
        return bool(self.reason)

    def describe(self):
        """One line: where the readable part ends and how much was lost."""
        if not self.lost:
            return (f'no metadata.yaml: topics and counts rebuilt from {len(self.files)} storage '
                    f'file(s); {self.messages} messages read, nothing lost')
        read = self.last_time - self.first_time
        line = (f'damaged recording ({self.reason}): readable up to bag time {self.last_time:.3f} s, '
                f'{read:.2f} s and {self.messages} messages from its start; ')
        if isinstance(self.expected_messages, int):
            line += f'lost {max(self.expected_messages - self.messages, 0)} of {self.expected_messages} messages'
            if self.expected_duration:
                line += f' and {max(self.expected_duration - read, 0.0):.2f} s of {self.expected_duration:.2f} s'
        else:
            line += 'what followed is lost (no metadata.yaml to count it)'
        if self.unreadable_bytes:
            line += f'; {self.unreadable_bytes} bytes after the last whole record unreadable'
        return line


def storage_files(path):
    """The storage files of a recording directory (or the file itself), in recording order:
    metadata.yaml's list when it exists and names them, otherwise by name."""
    path = Path(path)
    if path.is_file():
        return [path]
    metadata = _metadata(path)
    listed = (metadata or {}).get('relative_file_paths') or []
    files = [path / name for name in listed if (path / name).is_file()]
    if not files:
        files = sorted((p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES),
                       key=lambda p: (len(p.stem), p.stem))
    return files


def _metadata(path):
    """The ``rosbag2_bagfile_information`` mapping of metadata.yaml, or None."""
    try:
        data = load_yaml((Path(path) / 'metadata.yaml').read_text())
    except (OSError, yaml.YAMLError):
        return None
    info = data.get('rosbag2_bagfile_information') if isinstance(data, dict) else None
    return info if isinstance(info, dict) else None


class SalvageReader:
    """Streams the readable part of a rosbag2 recording's storage files (see the module doc).

    The files are scanned once on opening (topics, message counts, where reading stops), then
    :meth:`messages` streams the same records again. Raises :class:`SalvageError` when not one
    message can be read.
    """

    def __init__(self, path):
        self.path = Path(path)
        self.files = storage_files(self.path)
        if not self.files:
            msg = f'{self.path}: no .mcap or .db3 storage file'
            raise SalvageError(msg)
        metadata = _metadata(self.path) if self.path.is_dir() else None
        self._topics, self._schemas = {}, {}  # (file index, storage id) -> (topic, type); -> name
        counts, first, last, read, reason, unreadable = {}, None, None, 0, '', None
        for index, file in enumerate(self.files):
            scan = _Scan()
            try:
                for topic, stamp, _ in self._records(index, file, scan):
                    counts[topic] = counts.get(topic, 0) + 1
                    first = stamp if first is None else min(first, stamp)
                    last = stamp if last is None else max(last, stamp)
                    read += 1
            except _Damaged as err:
                reason = f'{file.name}: {err}'
                unreadable = None if scan.end is None else file.stat().st_size - scan.end
                break
        self._readable_files = index + 1
        if not read:
            msg = f'{self.path}: no readable message ({reason or "the storage holds none"})'
            raise SalvageError(msg)
        topics = {}
        for topic, msgtype in self._topics.values():
            topics.setdefault(topic, msgtype)
        self.connections = [Connection(i, topic, msgtype, counts.get(topic, 0))
                            for i, (topic, msgtype) in enumerate(sorted(topics.items()))]
        self._by_topic = {c.topic: c for c in self.connections}
        self.start_time, self.end_time = first, last + 1
        self.duration = self.end_time - self.start_time
        expected_duration = ((metadata or {}).get('duration') or {}).get('nanoseconds')
        self.damage = Damage(tuple(f.name for f in self.files), reason, read, first / NANOSECONDS,
                             last / NANOSECONDS, (metadata or {}).get('message_count'),
                             None if expected_duration is None else expected_duration / NANOSECONDS,
                             unreadable, metadata is None)

    def messages(self, connections=None):
        """Yield (connection, bag time [ns], raw CDR) of the readable part, in storage order."""
        wanted = {c.topic for c in (connections or self.connections)}
        for index, file in enumerate(self.files[:self._readable_files]):
            try:
                for topic, stamp, raw in self._records(index, file, _Scan()):
                    if topic in wanted:
                        yield self._by_topic[topic], stamp, raw
            except _Damaged:
                return

    def close(self):
        """Nothing stays open between calls."""

    # ------------------------------------------------------------------ storages
    def _records(self, index, file, scan):
        """Yield (topic, bag time [ns], raw) of one storage file; raise _Damaged
        where reading stops, with ``scan.end`` the bytes read so far."""
        if file.suffix == '.mcap':
            yield from self._mcap(index, file, scan)
        else:
            yield from self._sqlite(index, file, scan)

    def _sqlite(self, index, file, scan):
        try:
            connection = sqlite3.connect(f'file:{file}?mode=ro', uri=True)
        except sqlite3.Error as err:
            raise _Damaged(f'cannot open: {err}') from err
        try:
            connection.execute('PRAGMA writable_schema=ON')  # tolerate a schema pointing past the end
            scan.end = None  # SQLite does not say at which byte a page broke
            try:
                for storage_id, name, msgtype in connection.execute('SELECT id, name, type FROM topics'):
                    self._topics[(index, storage_id)] = (name, msgtype)
                for storage_id, stamp, data in connection.execute(
                        'SELECT topic_id, timestamp, data FROM messages'):
                    topic = self._topics.get((index, storage_id))
                    if topic is not None:
                        yield topic[0], int(stamp), bytes(data)
            except sqlite3.Error as err:
                raise _Damaged(str(err)) from err
        finally:
            connection.close()

    def _mcap(self, index, file, scan):
        with file.open('rb') as stream:
            if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise _Damaged('not an MCAP file (no magic)')
            scan.end = len(MCAP_MAGIC)
            while True:
                header = stream.read(MCAP_RECORD_HEADER)
                if not header:
                    return  # ended cleanly between records (a file without summary or footer)
                if len(header) < MCAP_RECORD_HEADER:
                    raise _Damaged(f'cut inside a record header at byte {scan.end}')
                opcode, length = header[0], struct.unpack_from('<Q', header, 1)[0]
                body = stream.read(length)
                cut = len(body) < length
                if opcode == MCAP_DATA_END:
                    return
                try:
                    records, used = (self._mcap_chunk(body, cut) if opcode == MCAP_CHUNK
                                     else ([], 0) if cut else ([(opcode, body)], length))
                    found = [self._mcap_record(index, op, data) for op, data in records]
                except (struct.error, ValueError, UnicodeDecodeError) as err:
                    raise _Damaged(f'malformed record at byte {scan.end} ({err})') from err
                for message in found:
                    if message is not None:
                        yield message
                if cut:  # an uncompressed chunk gave the messages before the cut
                    where = scan.end
                    scan.end += MCAP_RECORD_HEADER + used if used else 0
                    raise _Damaged(f'cut inside the record at byte {where}')
                scan.end += MCAP_RECORD_HEADER + length

    @staticmethod
    def _mcap_chunk(body, cut=False):
        """(the (opcode, body) records inside a Chunk record, bytes of ``body`` they end at); of
        a chunk ``cut`` short, the whole records before the cut when it is uncompressed (none
        otherwise)."""
        size = struct.unpack_from('<Q', body, 16)[0]
        compression, offset = _string(body, MCAP_CHUNK_HEADER)
        length = struct.unpack_from('<Q', body, offset)[0]
        if cut and compression:
            return [], 0
        start_of_data = offset + 8
        data = (bytes(body[offset + 8:offset + 8 + length]) if cut
                else _decompress(body[offset + 8:offset + 8 + length], compression, size))
        records, offset = [], 0
        while offset + MCAP_RECORD_HEADER <= len(data):
            opcode, length = data[offset], struct.unpack_from('<Q', data, offset + 1)[0]
            start = offset + MCAP_RECORD_HEADER
            if start + length > len(data):
                if cut:
                    break
                raise ValueError('a record overruns its chunk')
            records.append((opcode, data[start:start + length]))
            offset = start + length
        return records, start_of_data + offset

    def _mcap_record(self, index, opcode, body):
        """A message (topic, log time [ns], raw) or None; learns schemas and channels."""
        if opcode == MCAP_SCHEMA:
            schema_id = struct.unpack_from('<H', body)[0]
            name, _ = _string(body, 2)
            self._schemas[(index, schema_id)] = name
        elif opcode == MCAP_CHANNEL:
            channel_id, schema_id = struct.unpack_from('<HH', body)
            topic, _ = _string(body, 4)
            msgtype = self._schemas.get((index, schema_id), '')
            self._topics[(index, channel_id)] = (topic, msgtype)
        elif opcode == MCAP_MESSAGE:
            channel_id, _, log_time, _ = struct.unpack_from('<HIQQ', body)
            topic = self._topics.get((index, channel_id))
            if topic is not None:
                return topic[0], log_time, body[MCAP_MESSAGE_HEADER:]
        return None


class _Damaged(Exception):
    """Reading a storage file stops here."""


class _Scan:
    """Bytes of a storage file read so far (None: the storage does not say)."""

    def __init__(self):
        self.end = 0


def _string(data, offset):
    """An MCAP string (uint32 length + UTF-8) at ``offset``: (text, offset after it)."""
    length = struct.unpack_from('<I', data, offset)[0]
    end = offset + 4 + length
    if end > len(data):
        raise ValueError('a string overruns its record')
    return bytes(data[offset + 4:end]).decode(), end


def _decompress(data, compression, size):
    """A chunk's records, decompressed as rosbags does it (``''``, ``lz4`` or ``zstd``)."""
    if compression == '':
        return bytes(data)
    from rosbags.rosbag2.storage_mcap import DECOMPRESSORS
    if compression not in DECOMPRESSORS:
        raise ValueError(f'unsupported chunk compression {compression!r}')
    raw = DECOMPRESSORS[compression](bytes(data), size)
    if len(raw) != size:
        raise ValueError('chunk size mismatch')
    return raw
