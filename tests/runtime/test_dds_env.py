"""Which DDS settings RORY's processes get: UDPv4 only, under every discovery range."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from rory_runtime.dds import fast_rediscovery_env

NS = {'f': 'http://www.eprosima.com'}


@pytest.mark.parametrize('reach', ['SUBNET', 'SYSTEM_DEFAULT', ''])
def test_outside_localhost_the_builtin_transports_are_udpv4(reach: str) -> None:
    env = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': reach})
    assert env['FASTDDS_BUILTIN_TRANSPORTS'] == 'UDPv4'
    assert Path(env['FASTRTPS_DEFAULT_PROFILES_FILE']).name == 'fast_rediscovery.xml'
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in env  # the operator's reach is kept


@pytest.mark.parametrize('reach', ['LOCALHOST', 'localhost'])
def test_localhost_is_made_with_a_udp_profile_on_the_loopback(reach: str) -> None:
    # Under LOCALHOST rmw_fastrtps brings shared memory back whatever the builtin transports
    # say; the same reach comes from SUBNET with UDPv4 bound to 127.0.0.1.
    env = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': reach})
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    profile = ET.parse(env['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    transports = profile.findall('.//f:transport_descriptor', NS)
    assert [t.findtext('f:type', namespaces=NS) for t in transports] == ['UDPv4']
    assert [a.text for a in profile.findall('.//f:interfaceWhiteList/f:address', NS)] == [
        '127.0.0.1']
    assert profile.findtext('.//f:useBuiltinTransports', namespaces=NS) == 'false'
    assert [a.text for a in profile.findall('.//f:initialPeersList//f:address', NS)] == [
        '127.0.0.1']


def test_the_two_profiles_agree_on_discovery_and_heartbeat() -> None:
    # The localhost profile differs in transports only.
    def timing(path: str) -> list[str]:
        root = ET.parse(path).getroot()
        parts = [root.find('.//f:discovery_config', NS), root.find('.//f:publisher', NS)]
        return [ET.canonicalize(ET.tostring(e), strip_text=True) for e in parts if e is not None]

    plain = fast_rediscovery_env({})['FASTRTPS_DEFAULT_PROFILES_FILE']
    local = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    assert len(timing(plain)) == 2
    assert timing(plain) == timing(local['FASTRTPS_DEFAULT_PROFILES_FILE'])


@pytest.mark.parametrize('reach', ['SUBNET', 'LOCALHOST'])
def test_the_supervisor_profile_differs_from_the_nodes_only_in_its_lease(reach: str) -> None:
    environ = {'ROS_AUTOMATIC_DISCOVERY_RANGE': reach}
    nodes = fast_rediscovery_env(environ)
    own = fast_rediscovery_env(environ, supervisor=True)
    assert {k: v for k, v in own.items() if k != 'FASTRTPS_DEFAULT_PROFILES_FILE'} == {
        k: v for k, v in nodes.items() if k != 'FASTRTPS_DEFAULT_PROFILES_FILE'}
    assert own['FASTRTPS_DEFAULT_PROFILES_FILE'] != nodes['FASTRTPS_DEFAULT_PROFILES_FILE']

    def lease(root: ET.Element) -> tuple[float, float]:
        def seconds(tag: str) -> float:
            element = root.find(f'.//f:discovery_config/f:{tag}', NS)
            assert element is not None
            return (float(element.findtext('f:sec', '0', NS))
                    + float(element.findtext('f:nanosec', '0', NS)) * 1e-9)
        return seconds('leaseDuration'), seconds('leaseAnnouncement')

    def without_lease(root: ET.Element) -> str:
        config = root.find('.//f:discovery_config', NS)
        assert config is not None
        for tag in ('leaseDuration', 'leaseAnnouncement'):
            config.remove(config.find(f'f:{tag}', NS))  # type: ignore[arg-type]
        return ET.canonicalize(ET.tostring(root), strip_text=True)

    node_root = ET.parse(nodes['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    own_root = ET.parse(own['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    # A killed node is forgotten within 1 s; the supervisor announces itself 4x less often.
    assert lease(node_root) == (1.0, 0.25)
    assert lease(own_root) == (3.0, 1.0)
    assert without_lease(own_root) == without_lease(node_root)
