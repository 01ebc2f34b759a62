"""Fast DDS kept where the rig says (``source.interface``): the XML profile that whitelists one
interface — 127.0.0.1 for ``loopback``, with unicast discovery through initial peers on
127.0.0.1 and no multicast, so nothing leaves the host — and the environment that makes this
process's next DDS participant use it (:func:`configure_fastdds`). ``all`` keeps Fast DDS's
defaults. Pure text and environment variables: no ROS 2 import (the tests' robot and viewer
use it too)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

from aoi3d.atomic import write_atomic

__all__ = ["LOOPBACK_PEERS", "configure_fastdds", "fastdds_profile", "profile_folder"]

_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- aoi3d: Fast DDS on {what} (services/ingest/fastdds.py) -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>aoi3d_udpv4</transport_id>
        <type>UDPv4</type>
        <interfaceWhiteList><address>{address}</address></interfaceWhiteList>
        <maxInitialPeersRange>{peers}</maxInitialPeersRange>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="aoi3d_{name}" is_default_profile="true">
      <rtps>
        <userTransports><transport_id>aoi3d_udpv4</transport_id></userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>{builtin}
      </rtps>
    </participant>
  </profiles>
</dds>
"""
_LOOPBACK_BUILTIN = """
        <builtin>
          <metatrafficUnicastLocatorList>
            <locator><udpv4><address>127.0.0.1</address></udpv4></locator>
          </metatrafficUnicastLocatorList>
          <initialPeersList>
            <locator><udpv4><address>127.0.0.1</address></udpv4></locator>
          </initialPeersList>
        </builtin>"""
LOOPBACK_PEERS = 32
"""Participants on the host that loopback discovery finds (Fast DDS tries this many ports)."""


def fastdds_profile(interface: str) -> str | None:
    """The Fast DDS XML profile for ``interface`` (``loopback``, ``all`` or an IPv4 address);
    None for ``all`` (Fast DDS's defaults)."""
    if interface == "all":
        return None
    if interface == "loopback":
        return _PROFILE.format(what="127.0.0.1 only, unicast discovery, no multicast",
                               address="127.0.0.1", peers=LOOPBACK_PEERS, name="loopback",
                               builtin=_LOOPBACK_BUILTIN)
    return _PROFILE.format(what=f"the interface {interface} only", address=interface,
                           peers=4, name="interface", builtin="")


def profile_folder() -> Path:
    """Where the profiles go by default: one folder of this user's under the temporary
    directory (the same file for every process: its content depends on the interface only),
    or a fresh temporary folder when someone else owns that one."""
    folder = Path(tempfile.gettempdir()) / f"aoi3d-fastdds-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        if folder.is_symlink() or folder.stat().st_uid != os.getuid():
            raise PermissionError(folder)
    except OSError:
        return Path(tempfile.mkdtemp(prefix="aoi3d-fastdds-"))
    return folder


def configure_fastdds(interface: str, directory: str | Path | None = None,
                      environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """Set (in ``environ``, default this process's environment) what makes the next DDS
    participant use ``interface``: Fast DDS as the middleware and its profile (written,
    atomically, under ``directory``, default :func:`profile_folder`). Returns the variables
    set. Must run before rclpy's first participant of the process."""
    env = os.environ if environ is None else environ
    out = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    xml = fastdds_profile(interface)
    if xml is not None:
        folder = Path(directory) if directory is not None else profile_folder()
        name = "loopback" if interface == "loopback" else f"interface-{interface}"
        path = folder / f"fastdds-{name}.xml"
        write_atomic(path, xml)
        out |= {"FASTDDS_DEFAULT_PROFILES_FILE": str(path),
                "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}
    env.update(out)
    return out
