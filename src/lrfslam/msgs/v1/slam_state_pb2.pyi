from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from lrfslam.msgs.v1 import features_pb2 as _features_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Landmark(_message.Message):
    __slots__ = ("id", "x_m", "y_m", "covariance_m2", "kind", "sightings", "confirmed")
    ID_FIELD_NUMBER: _ClassVar[int]
    X_M_FIELD_NUMBER: _ClassVar[int]
    Y_M_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_M2_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    SIGHTINGS_FIELD_NUMBER: _ClassVar[int]
    CONFIRMED_FIELD_NUMBER: _ClassVar[int]
    id: int
    x_m: float
    y_m: float
    covariance_m2: _containers.RepeatedScalarFieldContainer[float]
    kind: _features_pb2.FeatureKind
    sightings: int
    confirmed: bool
    def __init__(self, id: _Optional[int] = ..., x_m: _Optional[float] = ..., y_m: _Optional[float] = ..., covariance_m2: _Optional[_Iterable[float]] = ..., kind: _Optional[_Union[_features_pb2.FeatureKind, str]] = ..., sightings: _Optional[int] = ..., confirmed: _Optional[bool] = ...) -> None: ...

class SlamState(_message.Message):
    __slots__ = ("header", "pose", "pose_covariance", "landmarks", "scan_seq", "associated", "added", "rejected", "motion", "motion_matched")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    POSE_COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    SCAN_SEQ_FIELD_NUMBER: _ClassVar[int]
    ASSOCIATED_FIELD_NUMBER: _ClassVar[int]
    ADDED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    MOTION_MATCHED_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    pose: _common_pb2.Pose2D
    pose_covariance: _containers.RepeatedScalarFieldContainer[float]
    landmarks: _containers.RepeatedCompositeFieldContainer[Landmark]
    scan_seq: int
    associated: int
    added: int
    rejected: int
    motion: _common_pb2.Pose2D
    motion_matched: bool
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., pose: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., pose_covariance: _Optional[_Iterable[float]] = ..., landmarks: _Optional[_Iterable[_Union[Landmark, _Mapping]]] = ..., scan_seq: _Optional[int] = ..., associated: _Optional[int] = ..., added: _Optional[int] = ..., rejected: _Optional[int] = ..., motion: _Optional[_Union[_common_pb2.Pose2D, _Mapping]] = ..., motion_matched: _Optional[bool] = ...) -> None: ...
