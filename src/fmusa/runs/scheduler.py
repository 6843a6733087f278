"""Reaching a Dask scheduler: a wrong, dead or foreign address is a clear error within seconds, not a hang.

Dask's ``Client(address)`` retries a refused connection for 30 s and then raises a bare ``OSError``; its
timeout does not cover the handshake, so a server that accepts and never answers (a web server, the
scheduler's dashboard) holds it forever; and a server that answers otherwise can fail it with anything
(a ``MemoryError`` for an HTTP reply read as a frame length). :func:`connect_scheduler` tries a TCP address
with a plain socket first and gives Dask :data:`CONNECT_TIMEOUT_S` for the rest.
"""
from __future__ import annotations

import socket
import threading

from fmusa.errors import UsageError

#: Seconds to reach a Dask scheduler before giving up (Dask's own default, 30 s, is long to learn of a typo).
CONNECT_TIMEOUT_S = 5.0
_WHERE = "(--scheduler, or execution.scheduler in the study file)"
_NOT_DASK = "is it a Dask scheduler? (its port is 8786 by default; 8787 is its dashboard)"


class SchedulerUnreachableError(UsageError):
    """The Dask scheduler of ``--scheduler`` (or ``execution.scheduler``) cannot be reached, or its address
    is not one.

    Fix: start the scheduler (``dask scheduler --port 8786``) and pass the address it prints,
    ``tcp://HOST:PORT`` (not the dashboard's port 8787); or leave out ``--scheduler`` to run on local
    processes.
    """


def _unreachable(address: str, reason: str) -> SchedulerUnreachableError:
    return SchedulerUnreachableError(
        f"cannot reach the Dask scheduler at {address} {_WHERE}: {reason}; start it there (`dask scheduler`, "
        f"see README \"Run a study on a cluster\"), correct the address, or leave the scheduler out to run on "
        f"local worker processes. Nothing was run")


def connect_scheduler(address: str):
    """A ``dask.distributed.Client`` on the scheduler at ``address``, or :class:`SchedulerUnreachableError`
    naming the address, why, and the fix, within about :data:`CONNECT_TIMEOUT_S` seconds."""
    from dask.distributed import Client
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        host_port = parse_host_port(location) if scheme == "tcp" else None
    except ValueError as exc:
        raise SchedulerUnreachableError(
            f"{address!r} {_WHERE} is not a Dask scheduler address ({exc}); write it as tcp://HOST:PORT, e.g. "
            f"tcp://127.0.0.1:8786. Nothing was run") from None
    if host_port is not None:      # nothing listening: an error at once, not after Dask's retries
        try:
            socket.create_connection(host_port, timeout=CONNECT_TIMEOUT_S).close()
        except socket.timeout:
            raise _unreachable(address, f"no answer within {CONNECT_TIMEOUT_S:g} s") from None
        except OSError as exc:
            raise _unreachable(address, exc.strerror or str(exc) or type(exc).__name__) from None
    made: dict = {}

    def make() -> None:      # in a thread that is given up on in time: the handshake has no timeout
        try:
            made["client"] = Client(address, timeout=CONNECT_TIMEOUT_S)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            made["error"] = exc

    thread = threading.Thread(target=make, name="fmusa-dask-connect", daemon=True)
    thread.start()
    thread.join(CONNECT_TIMEOUT_S)
    if thread.is_alive():
        raise _unreachable(address, f"it accepts connections but does not answer as a Dask scheduler within "
                                    f"{CONNECT_TIMEOUT_S:g} s; {_NOT_DASK}")
    exc = made.get("error")
    if isinstance(exc, OSError):      # Dask's own timeout (a TimeoutError is an OSError)
        raise _unreachable(address, f"{str(exc).strip() or type(exc).__name__} (waited {CONNECT_TIMEOUT_S:g} s)")
    if isinstance(exc, Exception):    # a server that answers otherwise, or a TLS address without TLS settings
        raise _unreachable(address, f"Dask could not talk to it ({type(exc).__name__}: {str(exc).strip()[:200]}); "
                                    f"{_NOT_DASK}")
    if exc is not None:
        raise exc
    return made["client"]
