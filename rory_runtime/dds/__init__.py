"""DDS settings that make a restarted node rediscoverable fast (see fast_rediscovery.xml)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from importlib import resources


def fast_rediscovery_env(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for every process of a robot run under RORY (supervisor and nodes alike).

    UDPv4 only: after a SIGKILL, Fast DDS's shared-memory transport left the restarted process
    unheard for a median 2.8 s here, against 54 ms over UDPv4 (``python -m
    rory_eval.bench.discovery``), and a process killed holding a shared-memory port's mutex blocks
    every writer to that port for seconds
    (fast_rediscovery_localhost.xml). ``FASTDDS_BUILTIN_TRANSPORTS`` says UDPv4 - except under
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, where rmw_fastrtps brings shared memory back
    whatever the variable says; there the same reach is made with range SUBNET and a profile
    that allows only UDPv4 on 127.0.0.1.

    Args:
        environ: The environment the processes would otherwise get (default: this process's).
    """
    environ = os.environ if environ is None else environ
    files = resources.files(__package__)
    if environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').strip().upper() == 'LOCALHOST':
        return {
            'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET',
            'FASTRTPS_DEFAULT_PROFILES_FILE': str(files.joinpath('fast_rediscovery_localhost.xml')),
        }
    return {
        'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4',
        'FASTRTPS_DEFAULT_PROFILES_FILE': str(files.joinpath('fast_rediscovery.xml')),
    }


PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
"""Where Fast DDS reads its default profiles from (either name)."""


def node_profile_env(environ: Mapping[str, str]) -> dict[str, str]:
    """For a node process or standby started under ``environ``: RORY's node variant of the
    profile ``environ`` names, if it names one of RORY's own (``fast_rediscovery*_node.xml``:
    builtin writers asynchronous, so a cold node hears the supervisor's answer to its first
    announcement; see the file). A profile of the operator's own is left as it is: empty.
    """
    files = resources.files(__package__)
    own = {str(files.joinpath(name)): str(files.joinpath(name.replace('.xml', '_node.xml')))
           for name in ('fast_rediscovery.xml', 'fast_rediscovery_localhost.xml')}
    return {var: own[environ[var]] for var in PROFILE_VARIABLES if environ.get(var) in own}
