from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MapPose(_message.Message):
    __slots__ = ("header", "scan_seq", "pose", "map_from_slam", "keyframes", "closures", "closures_rejected", "local_pose", "localization", "pose_covariance")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    SCAN_SEQ_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    MAP_FROM_SLAM_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    CLOSURES_FIELD_NUMBER: _ClassVar[int]
    CLOSURES_REJECTED_FIELD_NUMBER: _ClassVar[int]
    LOCAL_POSE_FIELD_NUMBER: _ClassVar[int]
    LOCALIZATION_FIELD_NUMBER: _ClassVar[int]
    POSE_COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    scan_seq: int
    pose: _common_pb2.Pose2D
    map_from_slam: _common_pb2.Pose2D
    keyframes: int
    closures: int
    closures_rejected: int
    local_pose: _common_pb2.Pose2D
    localization: int
    pose_covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., scan_seq: _Optional[int] = ..., pose: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., map_from_slam: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., keyframes: _Optional[int] = ..., closures: _Optional[int] = ..., closures_rejected: _Optional[int] = ..., local_pose: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., localization: _Optional[int] = ..., pose_covariance: _Optional[_Iterable[float]] = ...) -> None: ...

class MapKeyframes(_message.Message):
    __slots__ = ("header", "scan_stamp_ns", "local_pose", "map_pose", "local_edge", "retired_scan_stamp_ns", "retired_local_pose", "retired_local_edge", "retired_anchor_stamp_ns", "retired_offset")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    SCAN_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    LOCAL_POSE_FIELD_NUMBER: _ClassVar[int]
    MAP_POSE_FIELD_NUMBER: _ClassVar[int]
    LOCAL_EDGE_FIELD_NUMBER: _ClassVar[int]
    RETIRED_SCAN_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    RETIRED_LOCAL_POSE_FIELD_NUMBER: _ClassVar[int]
    RETIRED_LOCAL_EDGE_FIELD_NUMBER: _ClassVar[int]
    RETIRED_ANCHOR_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    RETIRED_OFFSET_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    scan_stamp_ns: _containers.RepeatedScalarFieldContainer[int]
    local_pose: _containers.RepeatedScalarFieldContainer[float]
    map_pose: _containers.RepeatedScalarFieldContainer[float]
    local_edge: _containers.RepeatedScalarFieldContainer[bool]
    retired_scan_stamp_ns: _containers.RepeatedScalarFieldContainer[int]
    retired_local_pose: _containers.RepeatedScalarFieldContainer[float]
    retired_local_edge: _containers.RepeatedScalarFieldContainer[bool]
    retired_anchor_stamp_ns: _containers.RepeatedScalarFieldContainer[int]
    retired_offset: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., scan_stamp_ns: _Optional[_Iterable[int]] = ..., local_pose: _Optional[_Iterable[float]] = ..., map_pose: _Optional[_Iterable[float]] = ..., local_edge: _Optional[_Iterable[bool]] = ..., retired_scan_stamp_ns: _Optional[_Iterable[int]] = ..., retired_local_pose: _Optional[_Iterable[float]] = ..., retired_local_edge: _Optional[_Iterable[bool]] = ..., retired_anchor_stamp_ns: _Optional[_Iterable[int]] = ..., retired_offset: _Optional[_Iterable[float]] = ...) -> None: ...

class MapGrid(_message.Message):
    __slots__ = ("header", "resolution_m", "tile_cells", "whole", "tile_row", "tile_col", "cells", "keyframes", "pending")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_M_FIELD_NUMBER: _ClassVar[int]
    TILE_CELLS_FIELD_NUMBER: _ClassVar[int]
    WHOLE_FIELD_NUMBER: _ClassVar[int]
    TILE_ROW_FIELD_NUMBER: _ClassVar[int]
    TILE_COL_FIELD_NUMBER: _ClassVar[int]
    CELLS_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    resolution_m: float
    tile_cells: int
    whole: bool
    tile_row: _containers.RepeatedScalarFieldContainer[int]
    tile_col: _containers.RepeatedScalarFieldContainer[int]
    cells: bytes
    keyframes: int
    pending: int
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., resolution_m: _Optional[float] = ..., tile_cells: _Optional[int] = ..., whole: _Optional[bool] = ..., tile_row: _Optional[_Iterable[int]] = ..., tile_col: _Optional[_Iterable[int]] = ..., cells: _Optional[bytes] = ..., keyframes: _Optional[int] = ..., pending: _Optional[int] = ...) -> None: ...
