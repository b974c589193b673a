"""Play a contract bag into the calibrator: ``ros2 launch stellar_cal_ros calibrate_bag.launch.py``.

Arguments: ``bag:=BAG.mcap prior:=PRIOR.yaml [output:=RESULT.yaml] [rate:=0]
[effects:=radial_k3,time_offset] [checkpoint:=STATE.npz]``.  ``rate:=0`` plays as fast as
the calibrator keeps up (flow control on ``/calibrator/data_clock``).  Both nodes use the
bag's ``/clock`` (``use_sim_time``) only for their timers; the estimation uses the message
stamps.  Needs ``launch_ros`` (apt ``ros-jazzy-launch-ros``); not importable in a venv
without it.
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction, RegisterEventHandler, Shutdown
from launch.event_handlers import OnProcessExit
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution

from launch import LaunchDescription

try:
    from launch_ros.actions import Node
    from launch_ros.substitutions import FindPackageShare
except ImportError as exc:  # pragma: no cover - launch_ros is an apt package
    raise ImportError("calibrate_bag.launch.py needs launch_ros (ros-jazzy-launch-ros)") from exc


def effect_list(text: str) -> list[str]:
    """``effects:=radial_k3,time_offset`` (or ``[radial_k3, time_offset]``) as a list."""
    return [e.strip() for e in text.strip().strip("[]").split(",") if e.strip()]


def _calibrator(context, config):
    """The calibrator node, with ``effects`` split into the string list it declares."""
    params = {
        "prior_file": LaunchConfiguration("prior"),
        "output_file": LaunchConfiguration("output"),
        "checkpoint_file": LaunchConfiguration("checkpoint"),
        "use_sim_time": LaunchConfiguration("use_sim_time"),
    }
    effects = effect_list(LaunchConfiguration("effects").perform(context))
    if effects:  # an empty list has no type for the parameter: leave it unset then
        params["effects"] = effects
    return [Node(package="stellar_cal_ros", executable="calibrator", name="calibrator",
                 output="screen", parameters=[config, params])]


def generate_launch_description() -> LaunchDescription:
    """Player + calibrator; the calibrator stops (writing its result) when the player ends."""
    config = PathJoinSubstitution([FindPackageShare("stellar_cal_ros"), "config",
                                   "calibrator.yaml"])
    args = [
        DeclareLaunchArgument("bag", description="contract MCAP bag"),
        DeclareLaunchArgument("prior", description="prior calibration YAML"),
        DeclareLaunchArgument("output", default_value="calibration.yaml",
                              description="calibration YAML written at the end"),
        DeclareLaunchArgument("effects", default_value="",
                              description="comma-separated effect ids estimated on top of "
                                          "the method's baseline, e.g. radial_k3,time_offset"),
        DeclareLaunchArgument("checkpoint", default_value="",
                              description="filter checkpoint .npz ('' = none)"),
        DeclareLaunchArgument("rate", default_value="0.0",
                              description="playback rate (0: as fast as the calibrator "
                                          "keeps up)"),
        DeclareLaunchArgument("use_sim_time", default_value="true",
                              description="timers on the bag's /clock"),
    ]
    calibrator = OpaqueFunction(function=_calibrator, args=[config])
    player = Node(
        package="stellar_cal_ros", executable="player", name="player", output="screen",
        parameters=[{
            "bag": LaunchConfiguration("bag"),
            "rate": LaunchConfiguration("rate"),
            "progress_topic": "/calibrator/data_clock",
            "match_topic": "/calibrator/inputs_matched",
            # the handshake also waits for the calibrator's start-up (> 20 s at load ~20)
            "wait_for_subscribers_s": 60.0,
        }],
    )
    stop_when_played = RegisterEventHandler(OnProcessExit(
        target_action=player, on_exit=[Shutdown(reason="bag played")]))
    return LaunchDescription([*args, calibrator, player, stop_when_played])
