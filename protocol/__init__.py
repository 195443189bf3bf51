"""Shared wire protocol: message schemas, their codec, key expressions, session helper."""

from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import (Command, LidarConfig, Mission, MapMsg, Outcome, Pose, Scan, Tick)  # noqa: F401
