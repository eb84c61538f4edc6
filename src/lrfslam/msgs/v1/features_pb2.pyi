from lrfslam.msgs.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FeatureKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FEATURE_UNKNOWN: _ClassVar[FeatureKind]
    FEATURE_FORWARD: _ClassVar[FeatureKind]
    FEATURE_BACKWARD: _ClassVar[FeatureKind]
FEATURE_UNKNOWN: FeatureKind
FEATURE_FORWARD: FeatureKind
FEATURE_BACKWARD: FeatureKind

class Feature(_message.Message):
    __slots__ = ("kind", "x_m", "y_m", "covariance_m2", "beam", "angle_deg")
    KIND_FIELD_NUMBER: _ClassVar[int]
    X_M_FIELD_NUMBER: _ClassVar[int]
    Y_M_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_M2_FIELD_NUMBER: _ClassVar[int]
    BEAM_FIELD_NUMBER: _ClassVar[int]
    ANGLE_DEG_FIELD_NUMBER: _ClassVar[int]
    kind: FeatureKind
    x_m: float
    y_m: float
    covariance_m2: _containers.RepeatedScalarFieldContainer[float]
    beam: int
    angle_deg: float
    def __init__(self, kind: _Optional[_Union[FeatureKind, str]] = ..., x_m: _Optional[float] = ..., y_m: _Optional[float] = ..., covariance_m2: _Optional[_Iterable[float]] = ..., beam: _Optional[int] = ..., angle_deg: _Optional[float] = ...) -> None: ...

class WallDirection(_message.Message):
    __slots__ = ("direction_rad", "sigma_rad")
    DIRECTION_RAD_FIELD_NUMBER: _ClassVar[int]
    SIGMA_RAD_FIELD_NUMBER: _ClassVar[int]
    direction_rad: float
    sigma_rad: float
    def __init__(self, direction_rad: _Optional[float] = ..., sigma_rad: _Optional[float] = ...) -> None: ...

class Features(_message.Message):
    __slots__ = ("header", "scan_seq", "features", "wall_direction")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    SCAN_SEQ_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    WALL_DIRECTION_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    scan_seq: int
    features: _containers.RepeatedCompositeFieldContainer[Feature]
    wall_direction: WallDirection
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., scan_seq: _Optional[int] = ..., features: _Optional[_Iterable[_Union[Feature, _Mapping]]] = ..., wall_direction: _Optional[_Union[WallDirection, _Mapping]] = ...) -> None: ...
