"""The training viewer (`stg-train --viewer [PORT]`): stg-view showing the model while it trains.

`TrainingViewer` is a Trainer.train callback. After the first step it serves the current parameters
(export.trainer_model: an in-memory runtime Model, rendered by the CPU Player) and then refreshes
them every `every` seconds and after the last step; its status panel shows the step, loss, PSNR and
Gaussians. It only copies the parameters: the run, and its final model, are the same as without it.
Its rendering shares the cores with training, so it renders only when something changed (a new
snapshot, the browser's camera, the time or the mode); docs/viewer.md gives the measured slowdown.
Needs the viewer extra (viser); stg_runtime.viewer is imported only when a TrainingViewer is made.
"""
from __future__ import annotations

import sys
import time

from .export import trainer_model

#: Seconds between two snapshots of the parameters shown by default.
EVERY_SECONDS = 5.0


def progress_text(trainer) -> str:
    """The status panel's markdown: step of total, loss, PSNR, Gaussians, training seconds."""
    last = trainer.history[-1] if trainer.history else {}
    loss = f"{last['loss']:.4f}" if "loss" in last else "-"
    psnr = f"{last['psnr']:.2f} dB" if "psnr" in last else "-"
    return (f"**training**: step {trainer.step} of {trainer.steps}  \n"
            f"loss {loss}, PSNR {psnr} (batch)  \n"
            f"{trainer.params.count:,} Gaussians, {trainer.seconds:.0f} s")


class TrainingViewer:
    """Serves the model being trained at http://host:port (see the module docstring). Made before
    training, it checks the port (stg_runtime.viewer.server.PortInUse) so that a taken port fails the
    run at once; it serves from the first callback on. close() stops it."""

    def __init__(self, port: int = 8080, host: str = "127.0.0.1", every: float = EVERY_SECONDS,
                 quiet: bool = False):
        from stg_runtime.viewer.server import check_port_free
        check_port_free(host, port)
        self.port, self.host, self.every, self.quiet = port, host, every, quiet
        self.viewer = None
        self.snapshots = 0
        self.seconds = 0.0  # spent in the callback (snapshots, status), on the training thread
        self._snapshot_at = self._status_at = 0.0

    def __call__(self, trainer) -> None:
        start = time.perf_counter()
        self._update(trainer)
        self.seconds += time.perf_counter() - start

    def _update(self, trainer) -> None:
        now = time.monotonic()
        last_step = trainer.step >= trainer.steps
        if self.viewer is None:
            from stg_runtime.viewer.server import Viewer
            self.viewer = Viewer(trainer_model(trainer), host=self.host, port=self.port, device="cpu")
            self.snapshots, self._snapshot_at = 1, now
            if not self.quiet:
                print(f"stg-train: the training viewer is at {self.viewer.url}", file=sys.stderr)
        elif last_step or now - self._snapshot_at >= self.every:
            self.viewer.set_model(trainer_model(trainer))
            self.snapshots, self._snapshot_at = self.snapshots + 1, now
        if last_step or now - self._status_at >= 0.5:
            self.viewer.set_status(progress_text(trainer))
            self._status_at = now

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.close()
