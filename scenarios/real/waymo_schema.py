"""The Waymo Open Motion ``Scenario`` protocol buffer, only the fields the reader uses.

The schema is built at run time from a ``FileDescriptorProto`` in a private descriptor
pool (no ``protoc``, no generated modules). Message and field names, numbers and types
follow the public ``scenario.proto`` and ``map.proto`` of waymo-research/waymo-open-dataset
(``src/waymo_open_dataset/protos/``, package ``waymo.open_dataset``, proto2). Fields not
listed here (lidar, camera tokens, traffic signal states, lane boundaries and neighbours,
stop signs, speed bumps, driveways, ...) are unknown to this schema and skipped by the
parser. The enum fields (``Track.object_type``, ``RequiredPrediction.difficulty``,
``LaneCenter.type``, ``RoadLine.type``, ``RoadEdge.type``) are declared ``int32``: the same
varint on the wire, so a value outside the published enum is read as its number (and
reported by the reader) rather than dropped.

Fields read (``field number: type``)::

    Scenario        scenario_id 5: string, timestamps_seconds 1: repeated double,
                    current_time_index 10: int32, tracks 2: repeated Track,
                    map_features 8: repeated MapFeature, sdc_track_index 6: int32,
                    objects_of_interest 4: repeated int32,
                    tracks_to_predict 11: repeated RequiredPrediction
    Track           id 1: int32, object_type 2: enum ObjectType (0 unset, 1 vehicle,
                    2 pedestrian, 3 cyclist, 4 other), states 3: repeated ObjectState
    ObjectState     center_x 2, center_y 3, center_z 4: double; length 5, width 6,
                    height 7, heading 8, velocity_x 9, velocity_y 10: float; valid 11: bool
    RequiredPrediction  track_index 1: int32, difficulty 2: enum (0 none, 1, 2)
    MapFeature      id 1: int64; oneof feature_data: lane 3: LaneCenter,
                    road_line 4: RoadLine, road_edge 5: RoadEdge, crosswalk 8: Crosswalk
    MapPoint        x 1, y 2, z 3: double
    LaneCenter      speed_limit_mph 1: double, type 2: enum, polyline 8: repeated MapPoint,
                    entry_lanes 9, exit_lanes 10: repeated int64 (packed)
    RoadLine        type 1: enum, polyline 2: repeated MapPoint
    RoadEdge        type 1: enum, polyline 2: repeated MapPoint
    Crosswalk       polygon 1: repeated MapPoint
"""

from __future__ import annotations

import functools

__all__ = ["OBJECT_TYPES", "scenario_class", "message_class"]

#: ``Track.object_type`` values by name (scenario.proto's ``ObjectType``)
OBJECT_TYPES = ("unset", "vehicle", "pedestrian", "cyclist", "other")

PACKAGE = "waymo.open_dataset"

# (message, [(field, number, type, label, message type or None, options)])
_D, _F, _I32, _I64, _B, _S, _M = "double", "float", "int32", "int64", "bool", "string", "message"
_OPT, _REP = "optional", "repeated"

_MESSAGES: dict[str, list[tuple]] = {
    "ObjectState": [
        ("center_x", 2, _D, _OPT, None),
        ("center_y", 3, _D, _OPT, None),
        ("center_z", 4, _D, _OPT, None),
        ("length", 5, _F, _OPT, None),
        ("width", 6, _F, _OPT, None),
        ("height", 7, _F, _OPT, None),
        ("heading", 8, _F, _OPT, None),
        ("velocity_x", 9, _F, _OPT, None),
        ("velocity_y", 10, _F, _OPT, None),
        ("valid", 11, _B, _OPT, None),
    ],
    "Track": [
        ("id", 1, _I32, _OPT, None),
        ("object_type", 2, _I32, _OPT, None),
        ("states", 3, _M, _REP, "ObjectState"),
    ],
    "RequiredPrediction": [
        ("track_index", 1, _I32, _OPT, None),
        ("difficulty", 2, _I32, _OPT, None),
    ],
    "MapPoint": [
        ("x", 1, _D, _OPT, None),
        ("y", 2, _D, _OPT, None),
        ("z", 3, _D, _OPT, None),
    ],
    "LaneCenter": [
        ("speed_limit_mph", 1, _D, _OPT, None),
        ("type", 2, _I32, _OPT, None),
        ("polyline", 8, _M, _REP, "MapPoint"),
        ("entry_lanes", 9, _I64, _REP, "packed"),
        ("exit_lanes", 10, _I64, _REP, "packed"),
    ],
    "RoadLine": [
        ("type", 1, _I32, _OPT, None),
        ("polyline", 2, _M, _REP, "MapPoint"),
    ],
    "RoadEdge": [
        ("type", 1, _I32, _OPT, None),
        ("polyline", 2, _M, _REP, "MapPoint"),
    ],
    "Crosswalk": [
        ("polygon", 1, _M, _REP, "MapPoint"),
    ],
    "MapFeature": [
        ("id", 1, _I64, _OPT, None),
        ("lane", 3, _M, _OPT, "LaneCenter", "feature_data"),
        ("road_line", 4, _M, _OPT, "RoadLine", "feature_data"),
        ("road_edge", 5, _M, _OPT, "RoadEdge", "feature_data"),
        ("crosswalk", 8, _M, _OPT, "Crosswalk", "feature_data"),
    ],
    "Scenario": [
        ("scenario_id", 5, _S, _OPT, None),
        ("timestamps_seconds", 1, _D, _REP, None),
        ("current_time_index", 10, _I32, _OPT, None),
        ("tracks", 2, _M, _REP, "Track"),
        ("map_features", 8, _M, _REP, "MapFeature"),
        ("sdc_track_index", 6, _I32, _OPT, None),
        ("objects_of_interest", 4, _I32, _REP, None),
        ("tracks_to_predict", 11, _M, _REP, "RequiredPrediction"),
    ],
}


@functools.lru_cache(maxsize=1)
def _pool():
    from google.protobuf import descriptor_pb2, descriptor_pool

    fd = descriptor_pb2.FileDescriptorProto(
        name="epo/waymo_open_dataset_scenario_subset.proto", package=PACKAGE, syntax="proto2"
    )
    F = descriptor_pb2.FieldDescriptorProto
    types = {
        _D: F.TYPE_DOUBLE,
        _F: F.TYPE_FLOAT,
        _I32: F.TYPE_INT32,
        _I64: F.TYPE_INT64,
        _B: F.TYPE_BOOL,
        _S: F.TYPE_STRING,
        _M: F.TYPE_MESSAGE,
    }
    labels = {_OPT: F.LABEL_OPTIONAL, _REP: F.LABEL_REPEATED}
    for name, spec in _MESSAGES.items():
        m = fd.message_type.add(name=name)
        oneofs: list[str] = []
        for field, number, kind, label, ref, *oneof in spec:
            f = m.field.add(name=field, number=number, type=types[kind], label=labels[label])
            if kind == _M:
                f.type_name = f".{PACKAGE}.{ref}"
            elif ref == "packed":
                f.options.packed = True
            if oneof:
                if oneof[0] not in oneofs:
                    oneofs.append(oneof[0])
                    m.oneof_decl.add(name=oneof[0])
                f.oneof_index = oneofs.index(oneof[0])
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    return pool


@functools.cache
def message_class(name: str):
    """The message class ``waymo.open_dataset.<name>`` of this schema (e.g. ``"MapPoint"``)."""
    from google.protobuf import message_factory

    return message_factory.GetMessageClass(_pool().FindMessageTypeByName(f"{PACKAGE}.{name}"))


def scenario_class():
    """The ``waymo.open_dataset.Scenario`` message class of this schema."""
    return message_class("Scenario")
