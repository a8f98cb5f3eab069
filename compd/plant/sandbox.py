"""What the packaged unit's IP sandbox does to the plant's connections, said in the lines that meet it.

The systemd units compd ships (systemd/compd.service, compd@.service) let IP traffic through
with localhost only (`IPAddressDeny=any`, `IPAddressAllow=localhost`); the network drop-in
(network.conf) adds the addresses of other hosts. compd cannot read its unit's properties
from inside, and systemd tells a service nothing of its sandbox, so it goes by what it can
see: a connect() that fails with EPERM ("Operation not permitted") was refused by this host
before any packet left, which is what the sandbox does (a local firewall's drop does the
same; a remote host or a firewall on the way refuses or times out instead), and a process
that systemd started (`INVOCATION_ID` in its environment) may be in that sandbox, so a server
listening on an address other than loopback is said to reach only what the unit allows.
"""

from __future__ import annotations

import errno
import ipaddress
import os

DROP_IN_DOC = 'docs/plant.md, "Other hosts under the packaged unit"'


def refused_by_this_host(e: BaseException) -> bool:
    """Whether a connect() failed with EPERM: refused on this host, before any packet left."""
    return isinstance(e, OSError) and e.errno == errno.EPERM


def connect_refused_hint(host: str) -> str:
    """What to do about a connect() to `host` that failed with EPERM."""
    return (
        f"refused by this host, not by {host}: the service's IP sandbox (the packaged unit allows"
        f" localhost only: IPAddressDeny=any) or a local firewall; install the network drop-in with"
        f" IPAddressAllow={host} ({DROP_IN_DOC})"
    )


def under_systemd(env: dict[str, str] | None = None) -> bool:
    """Whether systemd started this process (it sets INVOCATION_ID for every unit it runs)."""
    return "INVOCATION_ID" in (os.environ if env is None else env)


def is_loopback(address: str) -> bool:
    """Whether a bind address reaches this host only (127.0.0.0/8, ::1, `localhost`)."""
    if address.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(address.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may be any address


def listening_hint(what: str, bind: str, env: dict[str, str] | None = None) -> str | None:
    """For a server of compd's (`what`) listening on `bind`, what the packaged unit's sandbox lets
    reach it, when that may not be every host it listens for; None when it is (loopback, or not
    started by systemd)."""
    if is_loopback(bind) or not under_systemd(env):
        return None
    return (
        f"{what} listens on {bind}, but under the packaged unit only localhost reaches it"
        f" (IPAddressDeny=any, IPAddressAllow=localhost): clients on other hosts need the network"
        f" drop-in with their addresses in IPAddressAllow= ({DROP_IN_DOC}); their packets are dropped"
        f" before compd sees them, so nothing else is logged"
    )
