from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from lrfslam.msgs.v1 import slam_state_pb2 as _slam_state_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class SlamState(_message.Message):
    __slots__ = ("header", "pose", "pose_covariance", "changed_landmarks", "removed_landmark_ids", "landmarks", "confirmed_landmarks", "scan_seq", "associated", "added", "rejected", "motion", "motion_matched")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    POSE_COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    CHANGED_LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    REMOVED_LANDMARK_IDS_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    CONFIRMED_LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    SCAN_SEQ_FIELD_NUMBER: _ClassVar[int]
    ASSOCIATED_FIELD_NUMBER: _ClassVar[int]
    ADDED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    MOTION_MATCHED_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    pose: _common_pb2.Pose2D
    pose_covariance: _containers.RepeatedScalarFieldContainer[float]
    changed_landmarks: _containers.RepeatedCompositeFieldContainer[_slam_state_pb2.Landmark]
    removed_landmark_ids: _containers.RepeatedScalarFieldContainer[int]
    landmarks: int
    confirmed_landmarks: int
    scan_seq: int
    associated: int
    added: int
    rejected: int
    motion: _common_pb2.Pose2D
    motion_matched: bool
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., pose: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., pose_covariance: _Optional[_Iterable[float]] = ..., changed_landmarks: _Optional[_Iterable[_Union[_slam_state_pb2.Landmark, _Mapping]]] = ..., removed_landmark_ids: _Optional[_Iterable[int]] = ..., landmarks: _Optional[int] = ..., confirmed_landmarks: _Optional[int] = ..., scan_seq: _Optional[int] = ..., associated: _Optional[int] = ..., added: _Optional[int] = ..., rejected: _Optional[int] = ..., motion: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., motion_matched: _Optional[bool] = ...) -> None: ...

class LandmarkMap(_message.Message):
    __slots__ = ("header", "state_seq", "landmarks", "tolerance_m")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    STATE_SEQ_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    TOLERANCE_M_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    state_seq: int
    landmarks: _containers.RepeatedCompositeFieldContainer[_slam_state_pb2.Landmark]
    tolerance_m: float
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., state_seq: _Optional[int] = ..., landmarks: _Optional[_Iterable[_Union[_slam_state_pb2.Landmark, _Mapping]]] = ..., tolerance_m: _Optional[float] = ...) -> None: ...
