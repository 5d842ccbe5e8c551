"""robotics_msgs: the catkin build produces importable messages and service with the original's fields and constants."""

import importlib
import io
import os

import pytest

from tests.support.paths import REPO

ROOT = REPO


def test_messages_come_from_the_catkin_workspace():
    import robotics_msgs.msg
    import robotics_msgs.srv

    devel = os.path.join(ROOT, "build", "rcmp_ws", "devel")
    for module in (robotics_msgs.msg, robotics_msgs.srv):
        assert os.path.realpath(module.__file__).startswith(os.path.realpath(devel)), module.__file__


def test_cb_event_fields_and_constants():
    from robotics_msgs.msg import CB_Event

    assert CB_Event._type == "robotics_msgs/CB_Event"
    assert (CB_Event.CREATED, CB_Event.REMOVED) == (1, 0)
    assert list(zip(CB_Event.__slots__, CB_Event._slot_types)) == [("entity_name", "string"),
                                                                   ("entity_status", "int16")]


def test_robot_event_fields_and_constants():
    from robotics_msgs.msg import Robot_Event

    assert Robot_Event._type == "robotics_msgs/Robot_Event"
    assert (Robot_Event.CONNECTED, Robot_Event.DISCONNECTED) == (1, 0)
    assert list(zip(Robot_Event.__slots__, Robot_Event._slot_types)) == [("instance_name", "string"),
                                                                         ("instance_status", "int16")]


def test_firos_info_service_request_and_response():
    from robotics_msgs.srv import FIROS_Info, FIROS_InfoRequest, FIROS_InfoResponse

    assert FIROS_Info._type == "robotics_msgs/FIROS_Info"
    assert FIROS_Info._request_class is FIROS_InfoRequest and FIROS_Info._response_class is FIROS_InfoResponse
    assert list(zip(FIROS_InfoRequest.__slots__, FIROS_InfoRequest._slot_types)) == [("instance_name", "string")]
    assert list(zip(FIROS_InfoResponse.__slots__, FIROS_InfoResponse._slot_types)) == [("json_format", "string")]


@pytest.mark.parametrize("module, name, fields", [
    ("robotics_msgs.msg", "CB_Event", {"entity_name": "robot1", "entity_status": 1}),
    ("robotics_msgs.msg", "Robot_Event", {"instance_name": "robot_2", "instance_status": 0}),
    ("robotics_msgs.srv", "FIROS_InfoRequest", {"instance_name": "robot1"}),
    ("robotics_msgs.srv", "FIROS_InfoResponse", {"json_format": '{"robot1": {"topics": []}}'}),
])
def test_wire_round_trip(module, name, fields):
    message_class = getattr(importlib.import_module(module), name)
    buffer = io.BytesIO()
    message_class(**fields).serialize(buffer)
    copy = message_class().deserialize(buffer.getvalue())
    assert {slot: getattr(copy, slot) for slot in copy.__slots__} == fields
