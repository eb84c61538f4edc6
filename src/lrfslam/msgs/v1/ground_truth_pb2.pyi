from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class TrueCorner(_message.Message):
    __slots__ = ("id", "x_m", "y_m")
    ID_FIELD_NUMBER: _ClassVar[int]
    X_M_FIELD_NUMBER: _ClassVar[int]
    Y_M_FIELD_NUMBER: _ClassVar[int]
    id: int
    x_m: float
    y_m: float
    def __init__(self, id: _Optional[int] = ..., x_m: _Optional[float] = ..., y_m: _Optional[float] = ...) -> None: ...

class GroundTruth(_message.Message):
    __slots__ = ("header", "pose", "visible_corners", "world")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    VISIBLE_CORNERS_FIELD_NUMBER: _ClassVar[int]
    WORLD_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    pose: _common_pb2.Pose2D
    visible_corners: _containers.RepeatedCompositeFieldContainer[TrueCorner]
    world: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., pose: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., visible_corners: _Optional[_Iterable[_Union[TrueCorner, _Mapping]]] = ..., world: _Optional[str] = ...) -> None: ...
