"""A separate process that publishes or receives VGA depth frames, for the shared-memory tests.

``python -m tests.frame_peer pub ENDPOINT N``: publish N frames (frames=True), print
``published <n> shm <n>``. ``python -m tests.frame_peer sub ENDPOINT SECONDS [plain]``: count
frames for SECONDS, printing ``received <n> shmem_kib <RssShmem>`` after every second.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from schemas import codec, keys
from schemas.bus import Bus, TransportConfig

CELL = "t"
KEY = keys.depth(CELL, "cam1")


def shmem_kib() -> int:
    """Resident shared memory of this process (KiB), from /proc/self/status."""
    for line in open("/proc/self/status"):
        if line.startswith("RssShmem:"):
            return int(line.split()[1])
    return 0


def main(role: str, endpoint: str, arg: str, *rest: str) -> None:
    transport = TransportConfig(mode="client", connect=[endpoint], shared_memory="plain" not in rest)
    with Bus(transport, CELL) as bus:
        if role == "pub":
            pub = bus.publisher(KEY, frames=True)
            msg = codec.image_to_msg(np.ones((480, 640), np.uint16), 5, "cam1", "16UC1")
            time.sleep(0.5)  # let the router learn the subscriber
            for _ in range(int(arg)):
                pub.put(msg)
                time.sleep(0.02)
            print(f"published {pub.published} shm {pub.shm_puts}", flush=True)
        else:
            got = []
            bus.session.declare_subscriber(KEY, lambda sample: got.append(len(sample.payload)))
            print(f"ready shmem_kib {shmem_kib()}", flush=True)
            for _ in range(int(arg)):
                time.sleep(1.0)
                print(f"received {len(got)} shmem_kib {shmem_kib()}", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
