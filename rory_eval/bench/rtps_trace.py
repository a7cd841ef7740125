"""Who said what in DDS discovery: RTPS submessages read from a packet capture, one line each.

    tcpdump -i lo -w run.pcap udp portrange 29400-29649     # domain 88: 7400 + 250 * 88 ...
    python -m rory_eval.bench.rtps_trace run.pcap [--from EPOCH_SECONDS] [--to MS]

Prints, per RTPS submessage of interest (DATA, HEARTBEAT, ACKNACK, GAP), the time in ms from
``--from`` (a wall-clock time, e.g. the supervisor's spawn line), the sender's GUID prefix (its
last 8 bytes, which carry the process), the destination prefix when the message names one
(INFO_DST), the UDP port it went to, and the kind with its reader and writer entities, builtin
ones named (SPDP: participants, SEDP: endpoints, WLP: liveliness). How a cold start's discovery
was read (docs/performance.md, "A cold start: where the discovery went"). Reads classic pcap
files (what ``tcpdump -w`` writes), any link type: it finds each packet's RTPS header.
"""

from __future__ import annotations

import argparse
import struct
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

BUILTIN = {
    0x000100C2: 'SPDPw', 0x000100C7: 'SPDPr', 0x000003C2: 'SEDPpubW', 0x000003C7: 'SEDPpubR',
    0x000004C2: 'SEDPsubW', 0x000004C7: 'SEDPsubR', 0x000200C2: 'WLPw', 0x000200C7: 'WLPr',
    0: '-',
}
"""Builtin entity ids (RTPS 2.x, 9.3.1.3)."""

DATA, HEARTBEAT, ACKNACK, GAP, INFO_DST = 0x15, 0x07, 0x06, 0x08, 0x0E
KINDS = {DATA: 'DATA', HEARTBEAT: 'HB', ACKNACK: 'ACKNACK', GAP: 'GAP'}
PCAP_MAGIC = (0xA1B2C3D4, 0xA1B23C4D)  # microsecond and nanosecond timestamps


class TraceError(Exception):
    """The file is not a pcap capture."""


@dataclass(frozen=True)
class Submessage:
    """One submessage of interest."""

    time: float  # epoch seconds
    source: str  # sender's GUID prefix, last 8 bytes in hex
    destination: str | None
    port: int
    kind: str
    reader: str
    writer: str
    seq: int | None = None  # DATA only

    def line(self, origin: float) -> str:
        what = f'{self.kind}({self.reader}<-{self.writer}'
        what += f' sn={self.seq})' if self.seq is not None else ')'
        return (f'{(self.time - origin) * 1000:9.1f} {self.source} -> '
                f'{self.destination or "*"} :{self.port} {what}')


def entity(raw: bytes) -> str:
    value = struct.unpack('>I', raw)[0]
    return BUILTIN.get(value, f'{value:08x}')


def packets(data: bytes) -> Iterator[tuple[float, bytes]]:
    """(epoch seconds, bytes) of each packet of a classic pcap file."""
    if len(data) < 24:
        raise TraceError('too short for a pcap header')
    magic = struct.unpack('<I', data[:4])[0]
    if magic not in PCAP_MAGIC:
        raise TraceError('not a classic pcap file (tcpdump -w writes one)')
    fraction = 1e9 if magic == PCAP_MAGIC[1] else 1e6
    offset = 24
    while offset + 16 <= len(data):
        seconds, part, captured, _ = struct.unpack('<IIII', data[offset:offset + 16])
        offset += 16
        yield seconds + part / fraction, data[offset:offset + captured]
        offset += captured


def submessages(time: float, packet: bytes) -> Iterator[Submessage]:
    """The submessages of interest in one packet (none if it carries no RTPS)."""
    start = packet.find(b'RTPS')
    if start < 8:
        return
    port = struct.unpack('>H', packet[start - 6:start - 4])[0]  # UDP destination port
    rtps = packet[start:]
    source = rtps[8:20].hex()[-16:]
    destination = None
    at = 20
    while at + 4 <= len(rtps):
        kind, flags = rtps[at], rtps[at + 1]
        length = struct.unpack('<H' if flags & 1 else '>H', rtps[at + 2:at + 4])[0]
        body = rtps[at + 4:at + 4 + length]
        if kind == INFO_DST:
            destination = body[:12].hex()[-16:]
        elif kind in KINDS and len(body) >= 8:
            if kind == DATA and len(body) >= 20:
                high, low = struct.unpack('<iI', body[12:20])
                yield Submessage(time, source, destination, port, 'DATA', entity(body[4:8]),
                                 entity(body[8:12]), (high << 32) | low)
            elif kind != DATA:
                yield Submessage(time, source, destination, port, KINDS[kind],
                                 entity(body[0:4]), entity(body[4:8]))
        if length == 0:
            break  # the last submessage may say 0: to the end of the message
        at += 4 + length


def trace(data: bytes) -> list[Submessage]:
    """Every submessage of interest in a capture, in capture order."""
    return [sub for time, packet in packets(data) for sub in submessages(time, packet)]


def main(argv: Sequence[str] | None = None) -> int:
    """Print the trace."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.rtps_trace',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('capture', type=Path)
    parser.add_argument('--from', dest='origin', type=float, default=None,
                        help='epoch seconds that count as 0 (default: the first packet)')
    parser.add_argument('--to', type=float, default=None, help='stop after this many ms')
    args = parser.parse_args(argv)
    try:
        subs = trace(args.capture.read_bytes())
    except OSError as err:
        print(f'{args.capture}: {err.strerror}', file=sys.stderr)
        return 2
    except TraceError as err:
        print(f'{args.capture}: {err}', file=sys.stderr)
        return 2
    origin = args.origin if args.origin is not None else (subs[0].time if subs else 0.0)
    try:
        for sub in subs:
            if sub.time < origin or (args.to is not None
                                     and (sub.time - origin) * 1000 > args.to):
                continue
            print(sub.line(origin))
    except BrokenPipeError:  # piped into head
        sys.stderr.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
