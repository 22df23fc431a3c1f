"""ROS 2 message types for the cyclonedds test peer of `vlem ros2` (no ROS installation).

Rules: DDS type name = "<pkg>::msg::dds_::<Type>_" (note trailing underscore), every nested struct
needs its own typename too, field order == .msg order, ROS topic "/a/b" is DDS topic "rt/a/b".
uint8[] must be `types.sequence[types.uint8]`: a plain `bytes` annotation serializes fine but
Topic() creation fails ("Cannot construct typeobject for entity <class 'bytes'>", XTypes builder).
cyclonedds-python (de)serializes sequence[uint8] as a Python list of ints: ~38 ms to write and
~8 ms to read a 640x480 rgb8 image. `enable_fast_u8_sequences()` below patches that machine so
bytes/bytearray/memoryview values are written with one memcpy and uint8 sequences are read back
as `bytes` (same wire format; ~0.1-0.2 ms).
"""
from dataclasses import dataclass, field

import cyclonedds.idl.types as t
from cyclonedds.idl import IdlStruct

U8SEQ = t.sequence[t.uint8]


def enable_fast_u8_sequences():
    """Monkey-patch cyclonedds-python 11.0.1: uint8/byte sequences <-> `bytes` via memcpy."""
    from cyclonedds.idl import _machinery as mach

    cls = mach.PlainCdrV2SequenceOfPrimitiveMachine
    if getattr(cls, "_fast_u8", False):
        return
    orig_ser, orig_de = cls.serialize, cls.deserialize

    def serialize(self, buffer, value, *a, **k):
        if self.size == 1 and self.code == "B" and isinstance(value, (bytes, bytearray, memoryview)):
            assert self.max_length is None or len(value) <= self.max_length
            buffer.align(4)
            buffer.write("I", 4, len(value))
            buffer.write_bytes(value)
            return
        return orig_ser(self, buffer, value, *a, **k)

    def deserialize(self, buffer, *a, **k):
        if self.size == 1 and self.code == "B":
            buffer.align(4)
            return buffer.read_bytes(buffer.read("I", 4))
        return orig_de(self, buffer, *a, **k)

    cls.serialize, cls.deserialize, cls._fast_u8 = serialize, deserialize, True


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: t.uint32
    width: t.uint32
    encoding: str
    is_bigendian: t.uint8
    step: t.uint32
    data: U8SEQ


@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str
    offset: t.uint32
    datatype: t.uint8
    count: t.uint32
    INT8 = 1
    UINT8 = 2
    INT16 = 3
    UINT16 = 4
    INT32 = 5
    UINT32 = 6
    FLOAT32 = 7
    FLOAT64 = 8


@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header
    height: t.uint32
    width: t.uint32
    fields: t.sequence[PointField]
    is_bigendian: bool
    point_step: t.uint32
    row_step: t.uint32
    data: U8SEQ
    is_dense: bool


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped] = field(default_factory=list)


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: t.uint32 = 0
    y_offset: t.uint32 = 0
    height: t.uint32 = 0
    width: t.uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header
    height: t.uint32
    width: t.uint32
    distortion_model: str
    d: t.sequence[t.float64]
    k: t.array[t.float64, 9]
    r: t.array[t.float64, 9]
    p: t.array[t.float64, 12]
    binning_x: t.uint32 = 0
    binning_y: t.uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)
