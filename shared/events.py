"""Publishing the events of one job (a mission or an exploration) with a gap-free sequence."""

from __future__ import annotations

import threading
import cv2
import numpy as np

from shared.bus.typed import TypedBus
from shared.schemas import EventPayload, JobEvent, JobEventKind, JobState


def jpeg(image_rgb: np.ndarray, quality: int = 85) -> bytes:
    """RGB uint8 image -> JPEG bytes (what events carry for the dashboard)."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


class EventStream:
    """``seq`` starts at 0 and increases by one per event, so a listener can detect a gap.

    Events are published with a publisher-side cache (``CACHE_EVENTS``): a gateway that was down
    or restarted gets what it missed from the cache (zenoh-ext history/recovery), so a mission's
    record is complete even across a gateway crash.
    """

    CACHE_EVENTS = 2000

    def __init__(self, bus: TypedBus, key: str, job_id: str):
        self.bus, self.key, self.job_id = bus, key, job_id
        self._seq = 0
        self._lock = threading.Lock()
        self.state = JobState.QUEUED
        self.step = 0

    def emit(self, kind: JobEventKind, state: JobState, *, step: int | None = None,
             data: EventPayload | None = None, images: dict[str, bytes] | None = None) -> JobEvent:
        """``step`` None: the job's step so far (a final event of a job cancelled or failed at step 7
        says 7, not 0)."""
        with self._lock:
            step = self.step if step is None else max(step, 0)
            ev = JobEvent(job_id=self.job_id, seq=self._seq, kind=kind, state=state, step=step,
                              data=data, images=images or {})
            self._seq += 1
            self.state = state
            self.step = max(self.step, step)
            self.bus.publish(self.key, ev, cache=self.CACHE_EVENTS)
        return ev
