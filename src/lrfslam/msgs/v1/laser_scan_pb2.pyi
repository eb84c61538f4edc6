from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class BeamStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    BEAM_VALID: _ClassVar[BeamStatus]
    BEAM_NO_RETURN: _ClassVar[BeamStatus]
    BEAM_DAZZLE: _ClassVar[BeamStatus]
    BEAM_OVERFLOW: _ClassVar[BeamStatus]
    BEAM_INVALID: _ClassVar[BeamStatus]
BEAM_VALID: BeamStatus
BEAM_NO_RETURN: BeamStatus
BEAM_DAZZLE: BeamStatus
BEAM_OVERFLOW: BeamStatus
BEAM_INVALID: BeamStatus

class LaserScan(_message.Message):
    __slots__ = ("header", "angle_min_rad", "angle_increment_rad", "range_min_m", "range_max_m", "ranges_m", "status", "scan_time_s", "source")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    ANGLE_MIN_RAD_FIELD_NUMBER: _ClassVar[int]
    ANGLE_INCREMENT_RAD_FIELD_NUMBER: _ClassVar[int]
    RANGE_MIN_M_FIELD_NUMBER: _ClassVar[int]
    RANGE_MAX_M_FIELD_NUMBER: _ClassVar[int]
    RANGES_M_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    SCAN_TIME_S_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float
    ranges_m: _containers.RepeatedScalarFieldContainer[float]
    status: _containers.RepeatedScalarFieldContainer[BeamStatus]
    scan_time_s: float
    source: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., angle_min_rad: _Optional[float] = ..., angle_increment_rad: _Optional[float] = ..., range_min_m: _Optional[float] = ..., range_max_m: _Optional[float] = ..., ranges_m: _Optional[_Iterable[float]] = ..., status: _Optional[_Iterable[_Union[BeamStatus, str]]] = ..., scan_time_s: _Optional[float] = ..., source: _Optional[str] = ...) -> None: ...
