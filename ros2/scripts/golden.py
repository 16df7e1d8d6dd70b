"""Writes tests/golden/*.hex: the CDR bytes rclpy (Fast DDS) serialises the sample messages of
src/msgs.rs's golden test to. Run once, with the ROS 2 venv and the messages built by
build_msgs_py.sh:

    PYTHONPATH=OUT/python LD_LIBRARY_PATH=OUT/lib VENV/bin/python ros2/scripts/golden.py ros2/tests/golden [NAME ...]

With names (PlaceMatch, CameraInfo, ...) it writes only those: the others keep their bytes (Fast
DDS writes whatever its buffer held into alignment padding, different on every run).
"""

import sys
from pathlib import Path

from rclpy.serialization import serialize_message
from semlook_msgs.msg import LoopClosure, PlaceMatch
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header


def header():
    h = Header()
    h.stamp.sec, h.stamp.nanosec, h.frame_id = 1_700_000_123, 456_789, "cam0"
    return h


def samples():
    m = PlaceMatch()
    m.header = header()
    m.frame, m.place_id, m.place_index, m.score = 7, "ref/012", 12, 5.25
    m.sequence_matched, m.sequence_id, m.sequence_score, m.uniqueness, m.accepted = True, "ref/012", 1.5, 1.75, True
    m.top_ids, m.top_indices, m.top_scores = ["ref/012", "ref/013", "ref/0"], [12, 13, 0], [5.25, 4.5, -0.125]
    m.inliers, m.map_generation, m.latency_ms = 33, 3, 87.5
    m.has_relative_pose, m.relative_rotation, m.relative_translation = True, [0.0, 0.125, 0.0, 0.9921567416492215], [0.6, 0.0, 0.8]
    m.relative_rotation_deg, m.pose_inliers = 14.36, 57
    c = LoopClosure()
    c.header = header()
    c.query_id, c.place_id, c.place_index, c.score, c.uniqueness, c.inliers = "1700000123.000456789", "0", 0, 2.5, 1000.0, -1
    c.has_relative_pose, c.relative_rotation, c.relative_translation = False, [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0]
    c.relative_rotation_deg, c.pose_inliers = 0.0, -1
    i = Image()
    i.header = header()
    i.height, i.width, i.encoding, i.is_bigendian, i.step, i.data = 2, 3, "rgb8", 0, 9, bytes(range(18))
    j = CompressedImage()
    j.header = header()
    j.format, j.data = "jpeg", bytes([0xFF, 0xD8, 0xFF, 0xD9])
    p = PoseStamped()
    p.header = header()
    p.header.frame_id = "map"
    p.pose.position.x, p.pose.position.y, p.pose.position.z = 12.5, -3.25, 0.75
    o = p.pose.orientation
    o.x, o.y, o.z, o.w = 0.5, -0.5, 0.5, 0.5
    ci = CameraInfo()
    ci.header = header()
    ci.height, ci.width, ci.distortion_model = 540, 960, "plumb_bob"
    ci.d = [-0.25, 0.125, 0.001, -0.0005, 0.0]
    ci.k = [700.0, 0.0, 479.5, 0.0, 701.5, 269.5, 0.0, 0.0, 1.0]
    ci.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    ci.p = [690.25, 0.0, 480.0, -0.5, 0.0, 692.75, 270.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    ci.binning_x, ci.binning_y = 2, 3
    ci.roi.x_offset, ci.roi.y_offset, ci.roi.height, ci.roi.width, ci.roi.do_rectify = 8, 4, 500, 900, True
    return {"PlaceMatch": m, "LoopClosure": c, "Image": i, "CompressedImage": j, "PoseStamped": p, "CameraInfo": ci}


def main(out, names):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, msg in samples().items():
        if names and name not in names:
            continue
        b = serialize_message(msg)
        lines = [b[k : k + 16].hex(" ") for k in range(0, len(b), 16)]
        (out / f"{name}.hex").write_text("\n".join(lines) + "\n")
        print(f"{name}: {len(b)} bytes")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
