from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from lrfslam.msgs.v1 import laser_scan_pb2 as _laser_scan_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FilteredScan(_message.Message):
    __slots__ = ("header", "scan", "kept_beams", "x_m", "y_m", "max_range_m", "mode")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    SCAN_FIELD_NUMBER: _ClassVar[int]
    KEPT_BEAMS_FIELD_NUMBER: _ClassVar[int]
    X_M_FIELD_NUMBER: _ClassVar[int]
    Y_M_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_M_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    scan: _laser_scan_pb2.LaserScan
    kept_beams: _containers.RepeatedScalarFieldContainer[int]
    x_m: _containers.RepeatedScalarFieldContainer[float]
    y_m: _containers.RepeatedScalarFieldContainer[float]
    max_range_m: float
    mode: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., scan: _Optional[_Union[_laser_scan_pb2.LaserScan, _Mapping]] = ..., kept_beams: _Optional[_Iterable[int]] = ..., x_m: _Optional[_Iterable[float]] = ..., y_m: _Optional[_Iterable[float]] = ..., max_range_m: _Optional[float] = ..., mode: _Optional[str] = ...) -> None: ...
