"""The locate bench's counting of failures: alike reasons count together, whatever their figures."""

from vservo.core.study.locate_bench import failure_kind


def test_failures_count_together_by_their_words_and_the_joint_at_its_limit():
    servo = ("servo failed: robot_stopped (move refused: no joints within the limits reach the target (IK of 'flange' "
             "did not converge from 21 seeds: remaining error {} mm / 0.0 deg, joint_3 at its upper limit))")
    assert failure_kind(servo.format("0.1")) == failure_kind(servo.format("0.4")) == (
        "servo failed: robot_stopped, joint_3 at its upper limit")
    assert failure_kind(servo.replace("joint_3", "joint_2").format("0.1")) != failure_kind(servo.format("0.1"))
    assert failure_kind("servo failed: features_lost (corners lost in stage 3)") == "servo failed: features_lost"
