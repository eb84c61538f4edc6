from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class HealthLevel(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HEALTH_OK: _ClassVar[HealthLevel]
    HEALTH_WARN: _ClassVar[HealthLevel]
    HEALTH_ERROR: _ClassVar[HealthLevel]
    HEALTH_STALE: _ClassVar[HealthLevel]
HEALTH_OK: HealthLevel
HEALTH_WARN: HealthLevel
HEALTH_ERROR: HealthLevel
HEALTH_STALE: HealthLevel

class ServiceStatus(_message.Message):
    __slots__ = ("service", "robot", "level", "message", "wall_stamp_ns", "uptime_s", "counters", "last_data_stamp_ns", "config_json", "schemas", "pid", "host")
    class CountersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    LEVEL_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    WALL_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    UPTIME_S_FIELD_NUMBER: _ClassVar[int]
    COUNTERS_FIELD_NUMBER: _ClassVar[int]
    LAST_DATA_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    CONFIG_JSON_FIELD_NUMBER: _ClassVar[int]
    SCHEMAS_FIELD_NUMBER: _ClassVar[int]
    PID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    service: str
    robot: str
    level: HealthLevel
    message: str
    wall_stamp_ns: int
    uptime_s: float
    counters: _containers.ScalarMap[str, int]
    last_data_stamp_ns: int
    config_json: str
    schemas: _containers.RepeatedScalarFieldContainer[str]
    pid: int
    host: str
    def __init__(self, service: _Optional[str] = ..., robot: _Optional[str] = ..., level: _Optional[_Union[HealthLevel, str]] = ..., message: _Optional[str] = ..., wall_stamp_ns: _Optional[int] = ..., uptime_s: _Optional[float] = ..., counters: _Optional[_Mapping[str, int]] = ..., last_data_stamp_ns: _Optional[int] = ..., config_json: _Optional[str] = ..., schemas: _Optional[_Iterable[str]] = ..., pid: _Optional[int] = ..., host: _Optional[str] = ...) -> None: ...
