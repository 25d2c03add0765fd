#!/usr/bin/python3
"""A LinuxCNC "display" that runs a list of actions and writes what it saw (JSON).

LinuxCNC starts it as ``display.py -ini INI``; it runs under the system Python
(the ``linuxcnc`` and ``hal`` modules come with LinuxCNC, not with the venv).
The actions and the result file come from the environment:
``XMALIGN_HARNESS_ACTIONS`` (a JSON list) and ``XMALIGN_HARNESS_RESULT``.
Each action is a mapping with ``op``; see ``tests/linuxcnc/harness.py``.
When the display exits, LinuxCNC shuts down.
"""

import json
import os
import sys
import time
import traceback

import hal

import linuxcnc

POLL_S = 0.005
IDLE_S = 0.05


class ActionFailedError(Exception):
    pass


class Standstills:
    """Joint states at standstill during a program, each recorded once.

    Every poll reads each joint's ``pos-cmd``, ``vel-cmd``, ``motor-pos-cmd``,
    ``motor-offset`` and ``comp.N.out``: a comparator in the servo thread that
    latches the sign of the last non-zero ``vel-cmd`` (LinuxCNC's COMP_FILE
    direction, held at standstill), exact even when a move is shorter than a
    poll. When every ``vel-cmd`` is zero and two polls (milliseconds apart)
    read the same values, the joints have settled: one sample ``[[pos_cmd,
    motor_pos_cmd, motor_offset, direction], ...]`` per joint is kept (direction
    +1, -1, or 0 before the joint was seen moving), unless it repeats the last.
    Nothing is recorded while the program is paused: LinuxCNC's ramp of the
    COMP_FILE correction halts with the feed scale at 0 (``compute_screw_comp``
    in src/emc/motion/control.c, ``v_max = 0.5 * vel_limit * net_feed_scale``),
    so at an M0 the motor may stand nanometres short of the correction until the
    resume, by design.
    """

    NAMES = ("pos-cmd", "vel-cmd", "motor-pos-cmd", "motor-offset")

    def __init__(self, joints):
        self.joints = joints
        self.moved = [False] * joints
        self.previous = None
        self.samples = []

    def poll(self, paused):
        if not self.joints:
            return
        if paused:
            self.previous = None
            return
        read = [
            [float(hal.get_value(f"joint.{j}.{name}")) for name in self.NAMES]
            + [1 if hal.get_value(f"comp.{j}.out") else -1]
            for j in range(self.joints)
        ]
        for j, (_, velocity, _, _, _) in enumerate(read):
            self.moved[j] = self.moved[j] or velocity != 0.0
        settled = read == self.previous and not any(r[1] for r in read)
        self.previous = read
        if settled:
            sample = [
                [p, m, o, d if self.moved[j] else 0] for j, (p, _, m, o, d) in enumerate(read)
            ]
            if not self.samples or self.samples[-1] != sample:
                self.samples.append(sample)


class Display:
    def __init__(self):
        self.command = linuxcnc.command()
        self.stat = linuxcnc.stat()
        self.errors = linuxcnc.error_channel()
        self.messages = []
        # hal.get_value needs a component of this process
        self.component = hal.component("xmalign-harness-display")
        self.component.ready()

    def poll(self):
        self.stat.poll()
        message = self.errors.poll()
        while message:
            self.messages.append(message[1])
            message = self.errors.poll()
        return self.stat

    def wait_for(self, condition, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if condition(self.poll()):
                return
            time.sleep(POLL_S)
        raise ActionFailedError(f"timed out after {timeout_s} s waiting for {what}")

    def set_mode(self, mode):
        if self.poll().task_mode != mode:
            self.command.mode(mode)
            self.command.wait_complete()
            self.wait_for(lambda s: s.task_mode == mode, 5, f"task mode {mode}")

    def wait_received(self):
        """Until task has taken the last command."""
        serial = self.command.serial
        self.wait_for(lambda s: s.echo_serial_number >= serial, 5, "task to take the command")

    def wait_idle(self, timeout_s):
        """Until task has taken the last command and stays idle and in position for 50 ms."""
        serial = self.command.serial
        self.wait_for(lambda s: s.echo_serial_number >= serial, 5, "task to take the command")
        settled = []

        def idle(s):
            if s.interp_state == linuxcnc.INTERP_IDLE and s.inpos and not s.queue:
                settled.append(time.monotonic())
                return settled[-1] - settled[0] >= IDLE_S
            settled.clear()
            return False

        self.wait_for(idle, timeout_s, "the interpreter to be idle and the joints in position")

    # -- actions ---------------------------------------------------------------------
    def set_state(self, state, what):
        self.command.state(state)
        self.command.wait_complete()
        self.wait_for(lambda s: s.task_state == state, 5, what)

    def in_joint_mode(self, send, done, timeout_s, what):
        """``send(-1)`` (home or unhome all) in joint mode; wait until ``done(homed flags)``."""
        self.set_mode(linuxcnc.MODE_MANUAL)
        self.command.teleop_enable(0)
        self.command.wait_complete()
        send(-1)
        self.command.wait_complete()
        joints = self.poll().joints
        self.wait_for(lambda s: done(s.homed[:joints]), timeout_s, what)

    def op_estop_reset(self, action):
        self.set_state(linuxcnc.STATE_ESTOP_RESET, "estop reset")

    def op_machine_on(self, action):
        self.set_state(linuxcnc.STATE_ON, "machine on")

    def op_estop(self, action):
        self.set_state(linuxcnc.STATE_ESTOP, "estop")

    def op_home(self, action):
        self.in_joint_mode(self.command.home, all, action.get("timeout_s", 30), "homing")
        self.command.teleop_enable(1)
        self.command.wait_complete()

    def op_unhome(self, action):
        self.in_joint_mode(self.command.unhome, lambda homed: not any(homed), 5, "unhoming")

    def op_mdi(self, action):
        self.set_mode(linuxcnc.MODE_MDI)
        self.command.mdi(action["gcode"])
        self.command.wait_complete()
        self.wait_idle(action.get("timeout_s", 60))

    def op_pins(self, action):
        return {name: hal.get_value(name) for name in action["names"]}

    def op_setp(self, action):
        hal.set_p(action["name"], str(action["value"]))

    def op_sleep(self, action):
        time.sleep(action["seconds"])

    def op_run(self, action):
        """Run a program to its end, resuming after every M0; track pins' extremes.

        With ``standstill_joints``, also record the joints at every standstill
        (see ``Standstills``).
        """
        watch = action.get("watch", [])
        extremes = {name: 0.0 for name in watch}
        standstills = Standstills(action.get("standstill_joints", 0))
        if "feed_override" in action:
            self.command.feedrate(float(action["feed_override"]))
            self.command.wait_complete()
        self.set_mode(linuxcnc.MODE_AUTO)
        self.command.program_open(action["program"])
        self.command.wait_complete()
        # not wait_complete(): task completes AUTO_RUN/AUTO_RESUME only when the
        # interpreter stops again (next M0), so the polls below would miss the motion
        self.command.auto(linuxcnc.AUTO_RUN, 0)
        self.wait_received()
        started = time.monotonic()
        resumes = 0
        # a short program may be read to its end (interpreter idle) while motion still runs
        self.wait_for(
            lambda s: s.interp_state != linuxcnc.INTERP_IDLE or s.queue, 5, "the program start"
        )
        deadline = started + action.get("timeout_s", 120)
        while True:
            s = self.poll()
            for name in watch:
                value = abs(float(hal.get_value(name)))
                extremes[name] = max(extremes[name], value)
            standstills.poll(s.paused)
            if s.task_state != linuxcnc.STATE_ON:
                raise ActionFailedError(f"the machine went off during the program: {self.messages}")
            if s.interp_state == linuxcnc.INTERP_IDLE and not s.queue:
                break
            if s.paused and s.interp_state == linuxcnc.INTERP_PAUSED:
                self.command.auto(linuxcnc.AUTO_RESUME)
                self.wait_received()
                self.wait_for(lambda s: not s.paused, 5, "the program to resume")
                resumes += 1
            if time.monotonic() > deadline:
                raise ActionFailedError("the program did not end in time")
            time.sleep(POLL_S)
        return {
            "resumes": resumes,
            "seconds": time.monotonic() - started,
            "max_abs": extremes,
            "line": self.poll().current_line,
            "standstills": standstills.samples,
            "feed_override": self.poll().feedrate,
        }

    def state(self):
        s = self.poll()
        return {
            "task_state": s.task_state,
            "estop": bool(s.estop),
            "enabled": bool(s.enabled),
            "homed": [bool(h) for h in s.homed[: s.joints]],
            "joints": s.joints,
        }

    def run(self, actions):
        results = []
        for action in actions:
            op = action["op"]
            record = {"op": op, "label": action.get("label", op), "ok": True}
            try:
                record["value"] = getattr(self, "op_" + op)(action)
            except Exception as exc:  # noqa: BLE001 - reported to the harness
                record.update(ok=False, error=f"{type(exc).__name__}: {exc}")
                results.append(record)
                break
            results.append(record)
        return results


def main():
    with open(os.environ["XMALIGN_HARNESS_ACTIONS"]) as stream:
        actions = json.load(stream)
    out = {"results": [], "messages": [], "state": None, "crash": None}
    try:
        display = Display()
        display.wait_for(lambda s: s.task_state != 0, 20, "task to answer")
        out["results"] = display.run(actions)
        out["state"] = display.state()
        out["messages"] = display.messages
    except Exception:  # noqa: BLE001 - reported to the harness
        out["crash"] = traceback.format_exc()
    path = os.environ["XMALIGN_HARNESS_RESULT"]
    with open(path + ".part", "w") as stream:
        json.dump(out, stream)
    os.replace(path + ".part", path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
