"""The fault and refusal catalogue (core/production/protocol/catalogue.py): every kind the code
can raise has a plain sentence and an action.

The kinds are walked from the code itself: every ``CommandRefused(...)`` the product raises
names its kind (read from the source), every run's end names a RunEnd, every servo Failure
is a RunEnd, every safety refusal maps to a kind; then each kind goes through the
catalogue as the page says it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from vservo.core.production.manual_moves import SAFETY_REFUSALS
from vservo.core.production.protocol import Reply
from vservo.core.production.protocol.catalogue import REFUSALS, RUN_ENDS, Action, Refusal, RunEnd, explain, refusal_kind
from vservo.core.production.protocol.commands import CommandRefused
from vservo.core.robot.safety import SafetyRefusal
from vservo.core.servo.laws.base import Failure

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted(p for folder in ("core", "app") for p in (ROOT / folder).rglob("*.py"))


def _calls(name: str) -> list[tuple[Path, ast.Call]]:
    """Every call of ``name`` (a plain name or an attribute) in the product's source."""
    found = []
    for path in SOURCES:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call):
                callee = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
                if callee == name:
                    found.append((path, node))
    return found


def _kind_named(node: ast.Call, position: int, keyword: str, enum: str) -> str | None:
    """The member of ``enum`` a call passes at ``position`` or as ``keyword`` (None: not given)."""
    given = [k.value for k in node.keywords if k.arg == keyword]
    given += node.args[position : position + 1]
    for value in given:
        if isinstance(value, ast.Attribute) and isinstance(value.value, ast.Name) and value.value.id == enum:
            return value.attr
        if isinstance(value, ast.IfExp):  # GRIP_WEAK if gripped else NO_GRIP
            return ",".join(v.attr for v in (value.body, value.orelse) if isinstance(v, ast.Attribute))
        return "(computed)"
    return None


def test_every_kind_has_a_sentence_and_an_action():
    assert set(REFUSALS) == set(Refusal)
    assert set(RUN_ENDS) == set(RunEnd)
    for kind in (*Refusal, *RunEnd):
        explanation = explain(kind)
        assert explanation.sentence.endswith(".") and explanation.sentence[0].isupper(), kind
        assert isinstance(explanation.action, Action)


def test_every_servo_failure_is_a_run_end_with_its_sentence():
    for failure in Failure:
        assert explain(RunEnd(failure.value)).sentence


def test_every_refusal_the_controller_raises_names_its_kind():
    """Outside the commands' own field checks (a value out of range, the default), every
    CommandRefused the product raises says its kind: no refusal reaches the page unexplained."""
    raised = _calls("CommandRefused")
    assert len(raised) > 40
    kinds: set[str] = set()
    for path, node in raised:
        named = _kind_named(node, 1, "kind", "Refusal")
        if path.name == "commands.py" and named is None:
            continue  # the dataclasses' field checks: OUT_OF_RANGE
        assert named is not None, f"{path.relative_to(ROOT)}:{node.lineno}: a CommandRefused without its kind"
        kinds.update(named.split(","))
    kinds.discard("(computed)")  # manual_moves.move_refused: SAFETY_REFUSALS, walked below
    assert kinds <= {kind.name for kind in Refusal}
    for kind in kinds:
        assert explain(Refusal[kind]).sentence


def test_every_run_end_the_assembly_says_names_its_kind():
    ends = _calls("_end")
    assert len(ends) >= 12
    for path, node in ends:
        named = _kind_named(node, 2, "end", "RunEnd")
        assert named is not None and named != "(computed)" or "failure" in ast.unparse(node), (
            f"{path.relative_to(ROOT)}:{node.lineno}: a run's end without its kind"
        )


def test_every_safety_refusal_has_a_kind():
    def subclasses(cls: type) -> set[type]:
        return {cls, *(s for sub in cls.__subclasses__() for s in subclasses(sub))}

    for refusal in subclasses(SafetyRefusal) - {SafetyRefusal}:
        assert refusal in SAFETY_REFUSALS, refusal.__name__
        assert explain(SAFETY_REFUSALS[refusal]).sentence


@pytest.mark.parametrize("kind", list(Refusal))
def test_a_refusal_reads_as_its_sentence_and_action_without_a_doubled_prefix(kind):
    words = Reply(False, error="move refused: move refused: joint_3 ...", kind=kind).operator_words()
    explanation = explain(kind)
    assert words.startswith(explanation.sentence) and words.endswith(explanation.action.value)
    assert "refused" not in words.lower()


def test_the_apps_own_refusals_have_kinds():
    from vservo.app.roles import RoleRefused
    from vservo.app.teach_panel import PoseEntryError

    assert refusal_kind(RoleRefused("monitor")) is Refusal.CONTROL
    assert refusal_kind(PoseEntryError("six numbers")) is Refusal.OUT_OF_RANGE
    assert refusal_kind(CommandRefused("x", Refusal.NO_GRIP)) is Refusal.NO_GRIP
