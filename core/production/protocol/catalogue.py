"""What went wrong, in the operator's words, and what to do: one catalogue for the whole cell.

Every refusal the controller or the app can answer a command with has a kind
(``Refusal``), and every way a run can end has one (``RunEnd``: the servo's failures,
``vservo.core.servo.laws.base.Failure``, by their own values, and the run's other ends).
``explain`` gives each kind its ``Explanation``: one plain sentence an operator reads
without the code, and one ``Action`` (move the part into view, commission the cell,
press Reset, call the integrator, ...). The page shows the sentence and the action; the
engineer's line the controller wrote (the limit, the values, the equation) stays one
click away, in the Engineering fold.

tests/production/test_catalogue.py walks every kind the code can raise through it: no
kind without a sentence and an action.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Action(StrEnum):
    """What the operator does about it; the value is how the page says it."""

    MOVE_PART = "Move the part into the camera's view (Present part, or by hand), then try again."
    COMMISSION = "Commission the cell (Calibrate tab), then try again."
    RESET = "Press Reset."
    CALL_INTEGRATOR = "Call the cell's integrator: the Engineering fold has the detail for them."
    CORRECT_VALUE = "Correct the value (the range is in the Engineering fold) and press again."
    WAIT = "Wait until it ends (E-STOP stops it now)."
    FOLLOW_BANNER = "Do what the banner says first."
    ENTER_MANUAL = "Press Manual mode (or Begin teaching) first; leave it with Leave manual mode."
    JOINT_PATH = "Press Move there (joint path)."
    MOVE_TARGET = "Choose a target the arm reaches (move it as the sentence says), or press Home and start from there."
    SMALLER_STEP = "Choose a smaller step."
    CLEAR_ALARM = "Clear the alarm on the robot's pendant, then press Reset."
    MOVE_CUP = "Move the cup onto the middle of the part's top face (Cup on it), then press Test pick again."
    SUCTION_OFF = "Press Suction off first."
    CARRY_PART = "At the pick, press Suction on and carry the part into the metal part, then press again."
    TEACH_FIRST = "Teach the step the Teach tab names as Next first."
    TEACH_AGAIN = "Teach the job again on this cell (Teach tab)."
    REMOVE_PART = "Take the part out of the metal part, then press Reset."
    NEXT_PART = "Press Reset, present the next part and press Start."
    TAKE_CONTROL = "Enter the operator token and press Take control."
    WAIT_LOCKOUT = "Wait a minute, then enter the right token again."
    RESTART = "Restart vservo serve."
    NONE = "Nothing to do."


class Refusal(StrEnum):
    """Why a command was refused (the controller's CommandRefused, the app's own checks)."""

    OUT_OF_RANGE = "out_of_range"  # a field outside what the command takes, or not a value at all
    ESTOP_ACTIVE = "estop_active"
    BUSY = "busy"  # a run or commissioning moves the robot, or is still stopping
    NOT_NOW = "not_now"  # the cell's phase does not allow it
    NOT_MANUAL = "not_manual"  # a jog or a typed move outside teaching and manual mode
    ROBOT_ALARM = "robot_alarm"
    ROBOT_HELD = "robot_held"  # held after a fault or an e-stop: Reset releases it
    LINE_BLOCKED = "line_blocked"  # the straight line cannot, a joint-space path can
    UNREACHABLE = "unreachable"  # no joints within the limits reach the target
    OUTSIDE_WORKSPACE = "outside_workspace"
    STEP_TOO_LARGE = "step_too_large"
    TOO_FAST = "too_fast"
    JOINTS_DISAGREE = "joints_disagree"  # the controller's joints are not the arm model's for its pose
    MOVE_STOPPED = "move_stopped"  # the robot stopped short of the target
    NO_FIXTURE = "no_fixture"  # the cell cannot put a part down
    PART_PLACE = "part_place"  # the fixture refused the place (off the table, on the metal part)
    RESET_FAILED = "reset_failed"
    NOT_TAUGHT_YET = "not_taught_yet"  # a step taught relative to one not taught yet
    PART_NOT_SEEN = "part_not_seen"  # a capture without the corners (and spot) it needs
    NO_GRIP = "no_grip"  # a test pick whose vacuum sensor felt nothing
    GRIP_WEAK = "grip_weak"  # a test pick whose part fell during the lift
    CUP_HOLDS_PART = "cup_holds_part"
    CUP_EMPTY = "cup_empty"
    VACUUM_FAULT = "vacuum_fault"  # the vacuum cannot be switched or its sensor read
    JOB_PROBLEM = "job_problem"  # a job that cannot be loaded, retargeted or saved
    NOT_COMMISSIONED = "not_commissioned"  # Apply with nothing (good) commissioned
    CELL_NOT_COMMISSIONED = "cell_not_commissioned"  # a job taught through a measured model, on a cell never commissioned
    COMMISSION_SETUP = "commission_setup"  # the steps, the output file or the board
    CONTROL = "control"  # this browser is a monitor (app/roles.py)
    TOKEN_LOCKOUT = "token_lockout"  # too many wrong operator tokens from this address (app/roles.py)
    CHANNEL = "channel"  # the controller process is gone or did not answer
    INTERNAL = "internal"  # a bug: the traceback is in the controller's log


class RunEnd(StrEnum):
    """How a run ended, why: the servo's failures by their own values, then the run's other ends."""

    # vservo.core.servo.laws.base.Failure, value for value
    FEATURES_LOST = "features_lost"
    CAMERA_RETREAT = "camera_retreat"
    NO_PROGRESS = "no_progress"
    UNREACHABLE = "unreachable"
    SINGULAR_JACOBIAN = "singular_jacobian"
    ITERATION_LIMIT = "iteration_limit"
    ROBOT_STOPPED = "robot_stopped"
    # the run's own
    PLACED = "placed"
    NOT_FOUND_AT_CHECK = "not_found_at_check"
    BEYOND_TOLERANCE = "beyond_tolerance"
    OUTSIDE_POCKET = "outside_pocket"
    NO_GRIP = "no_grip"
    ROBOT_FAULT = "robot_fault"  # a move refused or failed outside the servo
    NO_NETWORK = "no_network"  # the job locates its part and the cell has no network
    LOCATE_FAILED = "locate_failed"
    GOAL_OUT_OF_REACH = "goal_out_of_reach"
    GRASP_OUT_OF_REACH = "grasp_out_of_reach"  # refused before the pick: no turn of the taught grasp in reach
    CAMERA_LOST = "camera_lost"
    ESTOPPED = "estopped"
    INTERRUPTED = "interrupted"  # the controller process died during the run
    INTERNAL_ERROR = "internal_error"  # a bug: the traceback is in the controller's log


@dataclass(frozen=True)
class Explanation:
    """A kind in the operator's words: what happened, and what to do."""

    sentence: str
    action: Action

    def words(self) -> str:
        """The sentence and the action, as a notice or the banner says them."""
        return self.sentence if self.action is Action.NONE else f"{self.sentence} {self.action.value}"


_E = Explanation
REFUSALS: dict[Refusal, Explanation] = {
    Refusal.OUT_OF_RANGE: _E("A value given is outside what the cell accepts.", Action.CORRECT_VALUE),
    Refusal.ESTOP_ACTIVE: _E("The e-stop holds the robot: nothing moves until it is reset.", Action.RESET),
    Refusal.BUSY: _E("A run or commissioning is using the robot.", Action.WAIT),
    Refusal.NOT_NOW: _E("The cell cannot do that in its present state.", Action.FOLLOW_BANNER),
    Refusal.NOT_MANUAL: _E("The arm is moved by hand only while teaching or in manual mode.", Action.ENTER_MANUAL),
    Refusal.ROBOT_ALARM: _E("The robot's controller is in alarm.", Action.CLEAR_ALARM),
    Refusal.ROBOT_HELD: _E("The robot is held (after a fault or an e-stop).", Action.RESET),
    Refusal.LINE_BLOCKED: _E(
        "The arm cannot go there in a straight line (a joint would pass its limit on the way), but it can on a joint path.",
        Action.JOINT_PATH,
    ),
    Refusal.UNREACHABLE: _E("The arm cannot reach that pose: a joint would have to pass its limit.", Action.MOVE_TARGET),
    Refusal.OUTSIDE_WORKSPACE: _E("That pose puts the arm or a tool outside the cell's safe box.", Action.MOVE_TARGET),
    Refusal.STEP_TOO_LARGE: _E("That move is larger than one step may be.", Action.SMALLER_STEP),
    Refusal.TOO_FAST: _E("That move is faster than the cell allows.", Action.CALL_INTEGRATOR),
    Refusal.JOINTS_DISAGREE: _E(
        "The robot's controller reports its joints other than the cell's arm model puts them for its pose.",
        Action.CALL_INTEGRATOR,
    ),
    Refusal.MOVE_STOPPED: _E("The robot stopped before it reached the target.", Action.RESET),
    Refusal.NO_FIXTURE: _E("This cell cannot put a part down: parts arrive by hand.", Action.MOVE_PART),
    Refusal.PART_PLACE: _E("A part cannot lie there (off the table, or on the metal part).", Action.CORRECT_VALUE),
    Refusal.RESET_FAILED: _E("Reset could not reach the robot or the camera.", Action.CALL_INTEGRATOR),
    Refusal.NOT_TAUGHT_YET: _E("A step this one depends on is not taught yet.", Action.TEACH_FIRST),
    Refusal.PART_NOT_SEEN: _E(
        "The camera does not see what this capture needs (the part's four corners, the laser spot).", Action.MOVE_PART
    ),
    Refusal.NO_GRIP: _E("Test pick: the vacuum sensor felt no part on the cup.", Action.MOVE_CUP),
    Refusal.GRIP_WEAK: _E("Test pick: the part fell off the cup during the lift.", Action.MOVE_CUP),
    Refusal.CUP_HOLDS_PART: _E("The cup holds a part already.", Action.SUCTION_OFF),
    Refusal.CUP_EMPTY: _E("The place pose is taught with the part on the cup, and the cup holds none.", Action.CARRY_PART),
    Refusal.VACUUM_FAULT: _E("The vacuum cannot be switched, or its sensor read.", Action.CALL_INTEGRATOR),
    Refusal.JOB_PROBLEM: _E("The job cannot be used as it is stored.", Action.TEACH_AGAIN),
    Refusal.NOT_COMMISSIONED: _E("There is no good commissioning to apply.", Action.COMMISSION),
    Refusal.CELL_NOT_COMMISSIONED: _E(
        "This job was taught on a commissioned cell, and this cell's model was never commissioned (or teach the job again here).",
        Action.COMMISSION,
    ),
    Refusal.COMMISSION_SETUP: _E("Commissioning cannot start as asked.", Action.CALL_INTEGRATOR),
    Refusal.CONTROL: _E("This browser is a read-only monitor.", Action.TAKE_CONTROL),
    Refusal.TOKEN_LOCKOUT: _E("Too many wrong operator tokens came from this address.", Action.WAIT_LOCKOUT),
    Refusal.CHANNEL: _E("The page has lost the cell's controller.", Action.RESTART),
    Refusal.INTERNAL: _E("The controller failed on this command (a fault in vservo).", Action.CALL_INTEGRATOR),
}

RUN_ENDS: dict[RunEnd, Explanation] = {
    RunEnd.FEATURES_LOST: _E("The camera lost the part during the servo (or there was no part to see).", Action.MOVE_PART),
    RunEnd.CAMERA_RETREAT: _E("The servo drove the camera away from the part: the cell's model looks wrong.", Action.COMMISSION),
    RunEnd.NO_PROGRESS: _E("The servo stopped getting closer to the taught view.", Action.COMMISSION),
    RunEnd.UNREACHABLE: _E(
        "The servo's next move was out of the arm's reach: the part lies too far from where it was taught.", Action.MOVE_PART
    ),
    RunEnd.SINGULAR_JACOBIAN: _E("The servo could not compute a move from what the camera saw.", Action.MOVE_PART),
    RunEnd.ITERATION_LIMIT: _E("The servo ran out of cycles before reaching the taught view.", Action.COMMISSION),
    RunEnd.ROBOT_STOPPED: _E("The robot refused or stopped a servo move (a safety limit, a hold or the link).", Action.RESET),
    RunEnd.PLACED: _E("The part is in the metal part.", Action.NEXT_PART),
    RunEnd.NOT_FOUND_AT_CHECK: _E("After the place, the camera did not find the part in the metal part.", Action.REMOVE_PART),
    RunEnd.BEYOND_TOLERANCE: _E("The part was placed farther from its taught place than the job allows.", Action.REMOVE_PART),
    RunEnd.OUTSIDE_POCKET: _E("The part was released outside the metal part's pocket.", Action.REMOVE_PART),
    RunEnd.NO_GRIP: _E("The cup did not grip the part at the pick.", Action.RESET),
    RunEnd.ROBOT_FAULT: _E("The robot refused or failed a move of the run.", Action.RESET),
    RunEnd.NO_NETWORK: _E("This job locates its part, and the cell has no network to locate it with.", Action.COMMISSION),
    RunEnd.LOCATE_FAILED: _E("The part was not found on the table.", Action.MOVE_PART),
    RunEnd.GOAL_OUT_OF_REACH: _E("The part lies where the arm cannot view it as taught.", Action.MOVE_PART),
    RunEnd.GRASP_OUT_OF_REACH: _E(
        "The part lies or is turned where the arm cannot pick it as taught; nothing was picked.", Action.MOVE_PART
    ),
    RunEnd.CAMERA_LOST: _E("The camera stopped delivering images; Reset opens it again.", Action.RESET),
    RunEnd.ESTOPPED: _E("The e-stop stopped the run; the robot is held.", Action.RESET),
    RunEnd.INTERRUPTED: _E("The controller stopped during the run.", Action.CALL_INTEGRATOR),
    RunEnd.INTERNAL_ERROR: _E("The run failed on a fault in vservo; the robot is held.", Action.CALL_INTEGRATOR),
}


def explain(kind: Refusal | RunEnd) -> Explanation:
    """The kind's sentence and action (every kind has one: the test walks them all)."""
    return REFUSALS[kind] if isinstance(kind, Refusal) else RUN_ENDS[kind]


def refusal_kind(exc: BaseException) -> Refusal:
    """The kind an exception refuses with: its own (CommandRefused and the app's checks carry
    one), a value out of range otherwise (the app's inputs: a pose typed, a template)."""
    kind = getattr(exc, "kind", None)
    return kind if isinstance(kind, Refusal) else Refusal.OUT_OF_RANGE
