"""rosbag2-compatible MCAP bag I/O (the only package part besides ``msgconv``/``nodes`` that
knows ROS message types): ``BagWriter``, ``BagReader``, ``message_class``."""

from .mcap_bag import (QOS_PRESETS, BagMessage, BagReader, BagWriter, TopicInfo,  # noqa: F401
                       message_class, resolve_qos)
from .msgdefs import message_definition, type_hash  # noqa: F401
