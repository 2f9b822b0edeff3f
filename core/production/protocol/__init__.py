"""The channel's protocol between the controller process and its apps: one contract, versioned.

- ``state``: what the controller publishes (ControllerState, its Phase, the teaching
  steps, the run's figures and outcome, commissioning's progress) and what it saw in a
  frame (FrameMeta);
- ``commands``: every command as a frozen dataclass that checks its own fields, registered
  by its name; the replies' records (jobs, runs);
- ``codec``: those typed values as JSON and back;
- ``client``: the messages and the app's end of the channel (ControllerClient).

It imports nothing of the controller (core/production/cell_controller.py and the server in
core/production/channel.py import it), and nothing heavy: the app's process stays light.
"""

from vservo.core.production.protocol.client import (
    KEY_ENVIRONMENT,
    PROTOCOL_VERSION,
    ChannelError,
    ControllerClient,
    Reply,
    new_key,
)
from vservo.core.production.protocol.commands import (
    COMMANDS,
    ApplyCommissioning,
    BeginTeach,
    CancelTeach,
    CaptureCheckView,
    CaptureDesired,
    Command,
    CommandRefused,
    Commission,
    Estop,
    GetJob,
    JobDetail,
    JobEntry,
    Jog,
    JogFrame,
    ListJobs,
    ListRuns,
    MoveTo,
    PresentPart,
    Query,
    Reset,
    RunEntry,
    SaveJob,
    SetPickPose,
    SetPlacePose,
    SetSettings,
    SetStartPose,
    Start,
    Suction,
    TestPick,
)
from vservo.core.production.protocol.state import (
    CommissioningProgress,
    CommissionStep,
    CommissionSummary,
    ControllerState,
    FrameMeta,
    Outcome,
    Phase,
    RunFigures,
    RunOutcome,
    Teaching,
    TeachStep,
)

__all__ = [
    "COMMANDS",
    "KEY_ENVIRONMENT",
    "PROTOCOL_VERSION",
    "ApplyCommissioning",
    "BeginTeach",
    "CancelTeach",
    "CaptureCheckView",
    "CaptureDesired",
    "ChannelError",
    "Command",
    "CommandRefused",
    "Commission",
    "CommissionStep",
    "CommissionSummary",
    "CommissioningProgress",
    "ControllerClient",
    "ControllerState",
    "Estop",
    "FrameMeta",
    "GetJob",
    "JobDetail",
    "JobEntry",
    "Jog",
    "JogFrame",
    "ListJobs",
    "ListRuns",
    "MoveTo",
    "Outcome",
    "Phase",
    "PresentPart",
    "Query",
    "Reply",
    "Reset",
    "RunEntry",
    "RunFigures",
    "RunOutcome",
    "SaveJob",
    "SetPickPose",
    "SetPlacePose",
    "SetSettings",
    "SetStartPose",
    "Start",
    "Suction",
    "TeachStep",
    "Teaching",
    "TestPick",
    "new_key",
]
