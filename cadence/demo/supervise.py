"""A service's process in the process cell, supervised the way systemd would: restarted when it dies,
stopped with one SIGTERM."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

from common.runtime.lifetime import PARENT_ENV
from services.registry import BY_NAME

RESTART_DELAY_S = 0.5


STOP_TIMEOUT_S = 15.0


@dataclass
class Supervised:
    """One service process, restarted when it dies (systemd's Restart=always, RestartSec=0.5)."""

    name: str
    env: dict[str, str]
    log: Path
    proc: asyncio.subprocess.Process | None = None
    restarts: int = 0
    exit_code: int | None = None  # at the end: after SIGTERM

    async def supervise(self, stopping: asyncio.Event, on_restart) -> None:
        """Until ``stopping``: never a start once it is set (a service that died just before the end was
        once started again after the stop had passed it, and ran alone until killed)."""
        with self.log.open("ab") as log:
            while not stopping.is_set():
                # from the loop's thread, and with PARENT_ENV: the service dies with the demo (SIGKILL too)
                # a session of its own: a terminal's Ctrl-C reaches the demo alone, which stops the services
                # in order with one SIGTERM each (a service's second signal forces its exit)
                self.proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    f"services.{self.name}",
                    env=self.env | {PARENT_ENV: str(os.getpid())},
                    stdout=log,
                    stderr=log,
                    start_new_session=True,
                    preexec_fn=unit.start_as_unit if (unit := BY_NAME.get(self.name)) else None,  # its Nice=
                )
                if stopping.is_set():  # the stop came while it started: it passed this process by
                    await self.stop()
                rc = await self.proc.wait()
                if stopping.is_set():
                    self.exit_code = rc
                    return
                self.restarts += 1
                on_restart(self.name, rc)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stopping.wait(), RESTART_DELAY_S)

    def kill(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.send_signal(signal.SIGKILL)

    async def stop(self) -> None:
        if self.proc is None or self.proc.returncode is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            await asyncio.wait_for(self.proc.wait(), STOP_TIMEOUT_S)
        except TimeoutError:
            self.proc.kill()
