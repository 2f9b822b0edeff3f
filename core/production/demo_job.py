"""The demo job that ships with vservo, taught on the shipped simulated cell.

``python -m vservo.core.production.demo_job`` writes static/jobs/demo.json and demo.png the way an
integrator teaches a job (Fig. C-2): jog the arm until the camera sees the part as it
should at the end of a servo, capture the desired image there; jog the cup onto the
part and store that motion as the pick transform; jog the held part into the metal
part and store the place pose; put the part in the pocket and capture the check view
over it (where a run looks at the part it placed); choose a start pose with the part in view. The jogging
here is computed from the shipped cell's layout, as the integrator's eyes would guide
it; the features and the laser depth come from the camera, as on the real cell.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from vservo.core.cell.config import CellConfig, load_cell
from vservo.core.geometry.spatial import Pose6, inverse, matrix_from_pose, rot_x, transform
from vservo.core.production.jobs import Job, TaughtModel, write_job_file
from vservo.core.production.placement_check import CheckView
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.robot.backend import apply_increment
from vservo.core.servo.teaching import TeachError, desired_from_features

# The camera 162 mm above the part's top face, its corners around the laser spot (the
# desired view of Table 5-2's second set).
DESIRED_cMo = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))
# Where assembly starts, as a base-frame increment of the desired view: 20 mm aside and
# turned 25 deg about the vertical (the UPJ's tool-down workspace is a thin shell:
# higher start poses are out of its reach).
START_OFFSET = transform(t=(0.02, 0.0, 0.0)) @ matrix_from_pose(Pose6(0.0, 0.0, 0.0, np.deg2rad(25.0), 0.0, 0.0))
# The cup is taught 3 mm into its level compensator, as an operator jogs until it presses.
PICK_PRESS_M = 0.003


def teach_demo_job(config: CellConfig) -> tuple[Job, np.ndarray, np.ndarray]:
    """The demo job, its desired image and its check image."""
    rig = simulated_rig(config)
    cell, robot, model = rig.cell, rig.robot, config.nominal
    assert cell is not None  # a simulated rig carries its plant
    scene = cell.state.scene
    side = scene.cube.side_m
    robot.connect()
    robot.servo(True)

    bMe_view = scene.cube.bMo @ inverse(DESIRED_cMo) @ inverse(model.eMc)
    robot.move_linear(bMe_view, 0.05)
    frame = rig.camera.read()
    features, _ = rig.extractor.extract(frame.image)
    desired = desired_from_features(features, model.camera, side)
    taught_bMe = robot.read_pose()

    # The cup on the middle of the top face, pointing down, its x along the part's edge.
    bMv_pick = scene.cube.bMo @ transform(rot_x(np.pi), (side / 2, side / 2, -PICK_PRESS_M))
    bMe_pick = bMv_pick @ inverse(model.eMv)
    # The part in the pocket: its bottom on the pocket floor, centred, edges along the pocket's.
    bMo_placed = scene.metal_part.bMp @ transform(t=(-side / 2, -side / 2, side))
    bMe_place = bMo_placed @ inverse(scene.cube.bMo) @ bMe_pick

    # The check view: the part put in the pocket by hand, the camera over it as in the
    # desired view (so it sees the part as large and as square as the servo did), then
    # the part put back on the table for the pick.
    bMo_table = scene.cube.bMo.copy()
    cell.place_cube(bMo_placed)
    check_bMe = bMo_placed @ inverse(DESIRED_cMo) @ inverse(model.eMc)
    robot.move_linear(check_bMe, 0.05)
    check_frame = rig.camera.read_after(robot.clock_s())
    check_features, _ = rig.extractor.extract(check_frame.image)
    if not check_features.all_corners_visible:
        raise TeachError("the check view does not show the part's four top-face corners")
    check = CheckView(check_bMe=robot.read_pose(), corners_px=check_features.corners_px)
    cell.place_cube(bMo_table)

    start_bMe = apply_increment(bMe_view, START_OFFSET)
    job = Job(
        name="demo",
        description="the 20 mm cube into the metal part's pocket on the shipped simulated cell",
        part_side_m=side,
        desired=desired,
        taught_bMe=taught_bMe,
        start_bMe=start_bMe,
        eMe_pick=inverse(taught_bMe) @ bMe_pick,
        bMe_place=bMe_place,
        check=check,
        taught_model=TaughtModel.of(model, config.model_measured),
    )
    rig.close()
    return job, frame.image, check_frame.image


def main(argv: list[str] | None = None) -> int:
    folder = Path(argv[0] if argv else Path(__file__).resolve().parents[2] / "static" / "jobs")
    job, image, check_image = teach_demo_job(load_cell())
    write_job_file(job, folder / "demo.json")
    cv2.imwrite(str(folder / "demo.png"), image)
    cv2.imwrite(str(folder / "demo.check.png"), check_image)
    print(f"wrote {folder / 'demo.json'}, demo.png and demo.check.png")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
