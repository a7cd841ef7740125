"""The RTPS trace reader on a capture built here: a packet with the RTPS header, an INFO_DST,
a DATA of the participant announcement and a HEARTBEAT of endpoint discovery."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from rory_eval.bench.rtps_trace import TraceError, main, trace

PREFIX = bytes(range(12))
OTHER = bytes(range(100, 112))


def _submessage(kind: int, body: bytes) -> bytes:
    return struct.pack('<BBH', kind, 0x01, len(body)) + body  # little endian (flag E)


def _packet() -> bytes:
    header = b'RTPS' + b'\x02\x03' + b'\x01\x0f' + PREFIX
    dst = _submessage(0x0E, OTHER)
    data_body = (b'\x00\x00\x10\x00' + bytes.fromhex('000100c7') + bytes.fromhex('000100c2')
                 + struct.pack('<iI', 0, 7) + b'payload!')
    hb_body = bytes.fromhex('000003c7') + bytes.fromhex('000003c2') + bytes(20)
    rtps = header + dst + _submessage(0x15, data_body) + _submessage(0x07, hb_body)
    udp = struct.pack('>HHHH', 40000, 29414, 8 + len(rtps), 0)
    return b'\x00' * 20 + udp + rtps  # an IPv4 header's worth of bytes, then UDP


def _pcap(packets: list[tuple[float, bytes]]) -> bytes:
    out = struct.pack('<IHHiIII', 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
    for time, packet in packets:
        out += struct.pack('<IIII', int(time), round((time % 1) * 1e6), len(packet),
                           len(packet)) + packet
    return out


def test_each_submessage_of_interest_is_named_with_its_endpoints() -> None:
    subs = trace(_pcap([(1000.5, _packet()), (1000.6, b'not rtps at all')]))
    assert [(s.kind, s.reader, s.writer, s.seq) for s in subs] == [
        ('DATA', 'SPDPr', 'SPDPw', 7), ('HB', 'SEDPpubR', 'SEDPpubW', None)]
    assert {s.source for s in subs} == {PREFIX.hex()[-16:]}
    assert {s.destination for s in subs} == {OTHER.hex()[-16:]}
    assert {s.port for s in subs} == {29414}
    assert subs[0].line(1000.0) == (f'    500.0 {PREFIX.hex()[-16:]} -> {OTHER.hex()[-16:]} '
                                    ':29414 DATA(SPDPr<-SPDPw sn=7)')


def test_a_file_that_is_not_a_capture_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / 'notes.txt'
    bad.write_text('hello, this is not a pcap file at all')
    assert main([str(bad)]) == 2
    said = capsys.readouterr().err.strip()
    assert said == f'{bad}: not a classic pcap file (tcpdump -w writes one)'
    with pytest.raises(TraceError):
        trace(b'short')
