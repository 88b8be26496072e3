"""rosbag2-compatible MCAP bag I/O (the only package part besides ``msgconv``/``nodes`` that
knows ROS message types): ``BagWriter``, ``BagReader``, ``message_class``, ``recover_bag``.
``interop`` checks a bag with independent readers (rosbags, mcap_ros2)."""

from .mcap_bag import (QOS_PRESETS, ROSBAG2_VERSION, BagMessage, BagReader,  # noqa: F401
                       BagWriter, TopicInfo, canonical_qos, message_class, qos_profiles,
                       recover_bag, resolve_qos)
from .msgdefs import message_definition, type_hash  # noqa: F401
