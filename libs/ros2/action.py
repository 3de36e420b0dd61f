"""ROS 2 actions over a :class:`~libs.ros2.node.Ros2Node`: a client and a server, in either key style.

ROS 2 has no action at the middleware level (rmw_zenoh ``docs/design.md``, "Actions"; the
zenoh-bridge-ros2dds maps them the same way): an action ``/name`` of type ``pkg/action/T`` is three
services and two topics under ``/name/_action/``:

* ``send_goal``   service ``T_SendGoal``  (UUID goal_id, T_Goal) -> (bool accepted, Time stamp)
* ``get_result``  service ``T_GetResult`` (UUID goal_id) -> (int8 status, T_Result); answered only when
  the goal ends, so it is a query that stays open for the goal's whole run
* ``cancel_goal`` service ``action_msgs/srv/CancelGoal`` (GoalInfo) -> (int8 return_code, GoalInfo[])
* ``feedback``    topic ``T_FeedbackMessage`` (UUID goal_id, T_Feedback)
* ``status``      topic ``action_msgs/msg/GoalStatusArray``, transient-local depth 1 (rcl_action's
  status QoS), republished on every change of any goal's status

In the rmw_zenoh style each of them is an ordinary service or topic key with its own RIHS01 hash and
liveliness token; in the bridge style the key is the name itself.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from . import messages as m
from .errors import Ros2ProtocolError
from .keys import Qos
from .node import Received, Ros2Node
from .transport import TransportError

log = logging.getLogger(__name__)

# The parts of an action under its name (rcl_action's fixed suffixes).
ACTION_PARTS = ("send_goal", "get_result", "cancel_goal", "feedback", "status")
# rcl_action_qos_profile_status_default: a late client learns every goal's status at once.
STATUS_QOS = Qos(transient_local=True, depth=1)
GOAL_STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"
CANCEL_GOAL = "action_msgs/srv/CancelGoal"


class GoalStatus(IntEnum):
    """action_msgs/msg/GoalStatus codes."""

    UNKNOWN = 0
    ACCEPTED = 1
    EXECUTING = 2
    CANCELING = 3
    SUCCEEDED = 4
    CANCELED = 5
    ABORTED = 6


TERMINAL = frozenset({GoalStatus.SUCCEEDED, GoalStatus.CANCELED, GoalStatus.ABORTED})


class CancelReturn(IntEnum):
    """action_msgs/srv/CancelGoal return codes."""

    NONE = 0
    REJECTED = 1
    UNKNOWN_GOAL_ID = 2
    GOAL_TERMINATED = 3


class ActionError(Ros2ProtocolError):
    """An action call failed at the protocol level (no server, a refused goal, a broken reply)."""


class GoalRejectedError(ActionError):
    """The action server refused the goal."""


def action_names(name: str) -> dict[str, str]:
    """The service and topic names of action ``name``, by part."""
    base = name.rstrip("/")
    return {part: f"{base}/_action/{part}" for part in ACTION_PARTS}


def new_goal_id() -> bytes:
    return uuid.uuid4().bytes


def _uuid(goal_id: bytes):
    import numpy as np

    return m.new("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(goal_id, np.uint8).copy())


def _goal_id(msg_uuid) -> bytes:
    return bytes(bytearray(msg_uuid.uuid))


def _goal_info(goal_id: bytes, stamp_s: float = 0.0):
    return m.new("action_msgs/msg/GoalInfo", goal_id=_uuid(goal_id), stamp=m.stamp(stamp_s))


def duration(seconds: float):
    """builtin_interfaces/Duration of ``seconds`` (>= 0)."""
    s = max(0.0, float(seconds))
    sec = int(s)
    return m.new("builtin_interfaces/msg/Duration", sec=sec, nanosec=int((s - sec) * 1e9) % 1_000_000_000)


def duration_s(d) -> float:
    return float(d.sec) + float(d.nanosec) * 1e-9


# --- client -------------------------------------------------------------------------------------------------


@dataclass
class ClientGoal:
    """One goal as the client follows it: status (from the status topic and the result), the newest
    feedback, the result when it arrived."""

    goal_id: bytes
    status: GoalStatus = GoalStatus.ACCEPTED
    result: Any = None  # T_Result, once get_result answered
    feedback: Any = None  # the newest T_Feedback
    feedback_count: int = 0
    done: threading.Event = field(default_factory=threading.Event)

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL

    def wait(self, timeout_s: float) -> bool:
        return self.done.wait(timeout_s)


class ActionClient:
    """Send goals, follow their feedback and status, ask their result, cancel them.

    ``result_timeout_s`` bounds each ``get_result`` query. It must be longer than zenoh's default
    query timeout: that query is open for the goal's whole run, and a 5 s timeout ends it before a
    navigation goal does (zenoh-plugin-ros2dds#413, #369; rmw_zenoh#173). A query that still times
    out (a bridge configured with its 5 s default) is asked again while the goal runs, and the status
    topic ends the goal even when no result arrives."""

    def __init__(self, node: Ros2Node, name: str, action_type: str, *, result_timeout_s: float = 300.0):
        self.node, self.name, self.action_type = node, name, action_type
        self.result_timeout_s = result_timeout_s
        names = action_names(name)
        self._send = node.client(names["send_goal"], f"{action_type}_SendGoal")
        self._result = node.client(names["get_result"], f"{action_type}_GetResult")
        self._cancel = node.client(names["cancel_goal"], CANCEL_GOAL)
        self._goals: dict[bytes, ClientGoal] = {}
        self._lock = threading.Lock()
        self._closed = threading.Event()
        node.subscribe(names["feedback"], f"{action_type}_FeedbackMessage", self._on_feedback, max_queue=64)
        node.subscribe(names["status"], GOAL_STATUS_ARRAY, self._on_status, STATUS_QOS, max_queue=64)

    # -- discovery --
    def server_present(self, timeout_s: float = 2.0) -> bool:
        """Whether an action server answers: a ``get_result`` for a goal id nobody sent. A server
        answers an unknown goal at once with status UNKNOWN (rclcpp_action does); no server, no reply.
        Unlike a cancel request it cannot touch a running goal."""
        req = m.new(f"{self.action_type}_GetResult_Request", goal_id=_uuid(new_goal_id()))
        try:
            self._result.call(req, timeout_s)
            return True
        except (TransportError, m.CdrError) as exc:
            log.info("no %s action server at %s: %s", self.action_type, self.name, exc)
            return False

    # -- goals --
    def send_goal(self, goal: Any, timeout_s: float = 10.0) -> ClientGoal:
        """Send ``goal``; the accepted goal is followed from here (its result is asked at once, on a
        worker, as rclcpp_action's client does). :class:`GoalRejectedError` when refused."""
        gid = new_goal_id()
        handle = ClientGoal(gid)
        with self._lock:
            self._goals[gid] = handle
        req = m.new(f"{self.action_type}_SendGoal_Request", goal_id=_uuid(gid), goal=goal)
        try:
            resp = self._send.call(req, timeout_s)
        except TransportError as exc:
            self._forget(gid)
            raise ActionError(f"{self.name}: send_goal got no answer: {exc}") from exc
        if not resp.accepted:
            self._forget(gid)
            raise GoalRejectedError(f"{self.name}: the action server rejected the goal")
        threading.Thread(target=self._follow_result, args=(handle,), name=f"action-result:{self.name}",
                         daemon=True).start()
        return handle

    def _forget(self, gid: bytes) -> None:
        with self._lock:
            self._goals.pop(gid, None)

    def _follow_result(self, handle: ClientGoal) -> None:
        req = m.new(f"{self.action_type}_GetResult_Request", goal_id=_uuid(handle.goal_id))
        while not handle.done.is_set() and not self._closed.is_set():
            t0 = time.monotonic()
            try:
                resp = self._result.call(req, self.result_timeout_s)
            except TransportError as exc:
                # No reply in time (a bridge's own query timeout, a link down): ask again, unless the
                # status topic has ended the goal meanwhile. Never faster than once a second.
                log.info("%s: get_result: %s; asking again", self.name, exc)
                self._closed.wait(max(0.0, 1.0 - (time.monotonic() - t0)))
                continue
            except m.CdrError as exc:
                log.warning("%s: a get_result reply that does not decode: %s", self.name, exc)
                self._closed.wait(1.0)
                continue
            status = GoalStatus(int(resp.status)) if int(resp.status) in GoalStatus._value2member_map_ else GoalStatus.UNKNOWN
            if status not in TERMINAL:
                # UNKNOWN: the server no longer (or not yet) knows the goal; the status topic decides.
                self._closed.wait(1.0)
                continue
            handle.result = resp.result
            self._finish(handle, status)
            return

    def _finish(self, handle: ClientGoal, status: GoalStatus) -> None:
        handle.status = status
        handle.done.set()
        self._forget(handle.goal_id)

    def _on_feedback(self, msg, _info: Received) -> None:
        with self._lock:
            handle = self._goals.get(_goal_id(msg.goal_id))
        if handle is not None:
            handle.feedback = msg.feedback
            handle.feedback_count += 1

    def _on_status(self, msg, _info: Received) -> None:
        for st in msg.status_list:
            with self._lock:
                handle = self._goals.get(_goal_id(st.goal_info.goal_id))
            if handle is None or handle.done.is_set():
                continue
            code = int(st.status)
            if code not in GoalStatus._value2member_map_:
                continue
            status = GoalStatus(code)
            if status in TERMINAL:
                # The result may still be on its way: give get_result a moment to bring the error
                # code, then end the goal on the status alone.
                timer = threading.Timer(0.5, lambda h=handle, s=status: None if h.done.is_set() else self._finish(h, s))
                timer.daemon = True
                timer.start()
                continue
            handle.status = status

    def cancel(self, handle: ClientGoal, timeout_s: float = 10.0) -> CancelReturn:
        """Ask the server to cancel one goal (goal id set, stamp zero: that goal only)."""
        req = m.new(f"{CANCEL_GOAL}_Request", goal_info=_goal_info(handle.goal_id))
        try:
            resp = self._cancel.call(req, timeout_s)
        except TransportError as exc:
            raise ActionError(f"{self.name}: cancel_goal got no answer: {exc}") from exc
        code = int(resp.return_code)
        return CancelReturn(code) if code in CancelReturn._value2member_map_ else CancelReturn.REJECTED

    def close(self) -> None:
        self._closed.set()


# --- server -------------------------------------------------------------------------------------------------


class ServerGoal:
    """One goal as the server runs it. The executor reads ``goal`` and ``cancel_requested``, sends
    feedback, and ends it once with :meth:`finish`."""

    def __init__(self, server: ActionServer, goal_id: bytes, goal: Any, accepted_s: float):
        self.server, self.goal_id, self.goal = server, goal_id, goal
        self.accepted_s = accepted_s
        self.status = GoalStatus.ACCEPTED
        self.result: Any = None
        self.cancel_requested = False
        self.done = threading.Event()

    def execute(self) -> None:
        self.server._set_status(self, GoalStatus.EXECUTING)

    def publish_feedback(self, feedback: Any) -> None:
        self.server._feedback.publish(m.new(f"{self.server.action_type}_FeedbackMessage",
                                            goal_id=_uuid(self.goal_id), feedback=feedback))

    def finish(self, status: GoalStatus, result: Any) -> None:
        if status not in TERMINAL:
            raise ValueError(f"a goal ends SUCCEEDED, CANCELED or ABORTED, not {status.name}")
        if self.done.is_set():
            return
        self.result = result
        self.server._set_status(self, status)
        self.done.set()


class ActionServer:
    """Serve an action: ``on_goal(goal) -> bool`` accepts or rejects, ``on_accepted(handle)`` hands the
    goal to its executor, ``on_cancel(handle) -> bool`` accepts a cancel request (the executor then
    sees ``cancel_requested`` and finishes the goal CANCELED). Ended goals are kept (``keep``) so that
    a late ``get_result`` is still answered."""

    def __init__(self, node: Ros2Node, name: str, action_type: str, *, on_goal: Callable[[Any], bool],
                 on_accepted: Callable[[ServerGoal], None], on_cancel: Callable[[ServerGoal], bool],
                 now_s: Callable[[], float] = time.time, result_wait_s: float = 600.0, keep: int = 32):
        self.node, self.name, self.action_type = node, name, action_type
        self._on_goal, self._on_accepted, self._on_cancel = on_goal, on_accepted, on_cancel
        self._now_s, self.result_wait_s, self._keep = now_s, result_wait_s, keep
        self._goals: OrderedDict[bytes, ServerGoal] = OrderedDict()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        names = action_names(name)
        self._status = node.publisher(names["status"], GOAL_STATUS_ARRAY, STATUS_QOS)
        self._feedback = node.publisher(names["feedback"], f"{action_type}_FeedbackMessage")
        node.serve(names["send_goal"], f"{action_type}_SendGoal", self._send_goal)
        node.serve(names["get_result"], f"{action_type}_GetResult", self._get_result)
        node.serve(names["cancel_goal"], CANCEL_GOAL, self._cancel_goal)

    def _send_goal(self, req):
        gid = _goal_id(req.goal_id)
        stamp = self._now_s()
        with self._lock:
            known = gid in self._goals
        ok = not known and not self._closed.is_set() and bool(self._on_goal(req.goal))
        if ok:
            handle = ServerGoal(self, gid, req.goal, stamp)
            with self._lock:
                self._goals[gid] = handle
                while len(self._goals) > self._keep:
                    old = next(iter(self._goals))
                    if not self._goals[old].done.is_set():
                        break
                    self._goals.pop(old)
            self._publish_status()
            self._on_accepted(handle)
        return m.new(f"{self.action_type}_SendGoal_Response", accepted=ok, stamp=m.stamp(stamp))

    def _get_result(self, req):
        with self._lock:
            handle = self._goals.get(_goal_id(req.goal_id))
        empty = m.new(f"{self.action_type}_GetResult_Response", status=int(GoalStatus.UNKNOWN),
                      result=_default(f"{self.action_type}_Result"))
        if handle is None:
            return empty  # an unknown goal: UNKNOWN at once (how a client finds out the server is there)
        end = time.monotonic() + self.result_wait_s
        while not handle.done.wait(0.2):
            if self._closed.is_set() or time.monotonic() > end:
                return empty
        return m.new(f"{self.action_type}_GetResult_Response", status=int(handle.status), result=handle.result)

    def _cancel_goal(self, req):
        gid = _goal_id(req.goal_info.goal_id)
        before_s = m.stamp_s(req.goal_info.stamp)
        zero = gid == bytes(16)
        with self._lock:
            goals = list(self._goals.values())
        # CancelGoal's rules: id and stamp zero: every goal; id zero: every goal accepted at or before
        # the stamp; an id: that goal (and, with a stamp, also those accepted at or before it).
        picked = [g for g in goals if (zero and (before_s == 0.0 or g.accepted_s <= before_s))
                  or (not zero and (g.goal_id == gid or (before_s > 0.0 and g.accepted_s <= before_s)))]
        if not zero and not any(g.goal_id == gid for g in goals):
            code = CancelReturn.UNKNOWN_GOAL_ID
            canceling = []
        else:
            live = [g for g in picked if not g.done.is_set()]
            canceling = [g for g in live if self._on_cancel(g)]
            for g in canceling:
                g.cancel_requested = True
                if g.status not in TERMINAL:
                    g.status = GoalStatus.CANCELING
            if canceling:
                self._publish_status()
            code = (CancelReturn.NONE if canceling else
                    CancelReturn.GOAL_TERMINATED if picked and not live else CancelReturn.REJECTED)
        return m.new(f"{CANCEL_GOAL}_Response", return_code=int(code),
                     goals_canceling=[_goal_info(g.goal_id, g.accepted_s) for g in canceling])

    def _set_status(self, handle: ServerGoal, status: GoalStatus) -> None:
        handle.status = status
        self._publish_status()

    def _publish_status(self) -> None:
        with self._lock:
            goals = list(self._goals.values())
        lst = [m.new("action_msgs/msg/GoalStatus", goal_info=_goal_info(g.goal_id, g.accepted_s), status=int(g.status))
               for g in goals]
        self._status.publish(m.new(GOAL_STATUS_ARRAY, status_list=lst))

    def active(self) -> list[ServerGoal]:
        with self._lock:
            return [g for g in self._goals.values() if not g.done.is_set()]

    def close(self) -> None:
        """Abort what still runs and release every waiting ``get_result``."""
        for g in self.active():
            g.finish(GoalStatus.ABORTED, _default(f"{self.action_type}_Result"))
        self._closed.set()


def _default(type_name: str) -> Any:
    """A message of ``type_name`` with every field at its zero value (a result nobody filled)."""
    import numpy as np

    from rosbags.typesys.store import Nodetype

    store = m.typestore()
    _consts, fields = store.fielddefs[type_name]
    values = {}
    numpy_types = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
                   "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
                   "float32": np.float32, "float64": np.float64, "byte": np.uint8, "char": np.uint8}
    for fname, desc in fields:
        kind, detail = desc
        if kind == Nodetype.BASE:
            t = detail[0]
            values[fname] = "" if t in ("string", "wstring") else (False if t == "bool" else 0.0 if t.startswith("float") else 0)
        elif kind == Nodetype.NAME:
            values[fname] = _default(detail)
        elif kind == Nodetype.ARRAY:
            (ekind, edetail), n = detail
            if ekind == Nodetype.BASE and edetail[0] in numpy_types:
                values[fname] = np.zeros(n, numpy_types[edetail[0]])
            else:
                values[fname] = [_zero(edetail) if ekind == Nodetype.NAME else "" for _ in range(n)]
        else:  # SEQUENCE
            (ekind, edetail), _n = detail
            values[fname] = (np.zeros(0, numpy_types[edetail[0]]) if ekind == Nodetype.BASE and edetail[0] in numpy_types
                             else [])
    return m.new(type_name, **values)
