"""An MCAP file read record by record from its start, for a file whose summary is missing or
unreadable (a recording killed before it closed the file, a copy cut short): what `mcap recover`
does, without rewriting the file.

mcap's StreamReader walks the records; chunks are taken whole (emit_chunks) and opened here, each
checked before it is decompressed (its declared size against its length) and after (its CRC), so
a damaged chunk is passed over instead of allocating what it claims. Reading stops at the first record that cannot be read; the
bytes from there to the end are reported as lost.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path


class LinearMcap:
    """The schemas, channels and message counts of an MCAP file read from its start (one pass
    here), and its messages in file order on each iteration. `stopped_at`: the byte where reading
    stopped (the file's size where it did not)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.schemas: dict = {}
        self.channels: dict = {}
        self.counts: dict[int, int] = {}
        self.stopped_at = 0
        self.damaged_chunks = 0
        for _ in self._messages(None, count=True):
            pass

    def _records(self, count: bool) -> Iterator:
        """Every schema, channel and message record in file order, chunks opened; it ends at the
        first record that cannot be read (`count`: note where, and the damaged chunks)."""
        from mcap.records import Chunk, DataEnd, Footer
        from mcap.stream_reader import StreamReader

        with open(self.path, "rb") as handle:
            records = StreamReader(handle, emit_chunks=True, record_size_limit=self.size).records
            end = 0
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    end = self.size
                    break
                except Exception:  # noqa: BLE001 - the cut, or bytes that are no record: all from `end` is lost
                    break
                if isinstance(record, (DataEnd, Footer)):
                    end = self.size
                    break
                if isinstance(record, Chunk):
                    inner = self._chunk_records(record)
                    if inner is None:  # its messages are lost; the next record may be whole
                        self.damaged_chunks += count
                    else:
                        yield from inner
                else:
                    yield record
                end = handle.tell()
        if count:
            self.stopped_at = end

    def _messages(self, topics, count: bool = False) -> Iterator[tuple]:
        """(schema, channel, message) of every message record (of `topics`, where given)."""
        from mcap.records import Channel, Message, Schema

        for record in self._records(count):
            if isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Message):
                channel = self.channels.get(record.channel_id)
                if count:
                    self.counts[record.channel_id] = self.counts.get(record.channel_id, 0) + 1
                if channel is not None and (topics is None or channel.topic in topics):
                    yield self.schemas.get(channel.schema_id), channel, record

    def _chunk_records(self, chunk) -> list | None:
        """The records of a chunk, or None when it cannot be opened: its declared size is checked
        against its length before mcap decompresses it, then its CRC and its records."""
        from mcap.stream_reader import breakup_chunk

        from voxtool.compression import check_expansion

        try:
            check_expansion(chunk.uncompressed_size, len(chunk.data), f"{self.path}: a chunk")
            return breakup_chunk(chunk, validate_crc=True)
        except Exception:  # noqa: BLE001 - any fault in a chunk's bytes: the chunk is lost
            return None

    def topics(self) -> dict[str, str]:
        return {c.topic: self.schemas[c.schema_id].name if c.schema_id in self.schemas else ""
                for c in self.channels.values()}

    def topic_counts(self) -> dict[str, int]:
        return {self.channels[cid].topic: n for cid, n in self.counts.items() if cid in self.channels}

    def iter_messages(self, topics, log_time_order: bool = True, starting_at=None) -> Iterator[tuple]:  # noqa: ARG002
        """mcap's reader interface, in file order (a recorder writes in time order)."""
        for schema, channel, message in self._messages(set(topics)):
            if starting_at is None or message.log_time >= starting_at:
                yield schema, channel, message

    def iter_decoded_messages(self, topics, log_time_order: bool = True, decoder_factory=None) -> Iterator[tuple]:  # noqa: ARG002
        decoders: dict = {}
        for schema, channel, message in self._messages(set(topics)):
            if schema.id not in decoders:
                decoders[schema.id] = decoder_factory.decoder_for(channel.message_encoding, schema)
            yield schema, channel, message, decoders[schema.id](message.data)

    def lost(self) -> str:
        """How much of the file could not be read (empty: all of it)."""
        lost = self.size - self.stopped_at
        if not lost and not self.damaged_chunks:
            return ""
        parts = []
        if lost:
            parts.append(f"the last {lost:,} of its {self.size:,} bytes could not be read (cut short, or not closed "
                         "by its recorder)")
        if self.damaged_chunks:
            parts.append(f"{self.damaged_chunks} damaged chunks were passed over")
        return "; ".join(parts)
