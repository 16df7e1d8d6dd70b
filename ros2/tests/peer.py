"""The ROS 2 peer of the node's interop test: a real rclpy node (Fast DDS) that publishes camera
frames to semlook_node and records the PlaceMatch messages it answers with.

    peer.py PLAN.json OUT.json

PLAN: {"frames": [{"kind": "jpeg"|"png"|"rgb8"|"bgr8"|"mono8"|"16UC1", "file": PATH,
        "width": W, "height": H, "sec": S, "nanosec": N}, ...],
       "wait": true|false,        # wait for each frame's answer before the next (else a burst)
       "expect": N,               # answers to wait for at the end
       "timeout": SECONDS,
       "camera_info": {"topic": T, "width": W, "height": H, "k": [9], "d": [...],
                       "distortion_model": M}}   # optional
Raw kinds read FILE as packed pixels (rgb8: RGB, bgr8: BGR, mono8: grey); jpeg/png send FILE's
bytes as a CompressedImage. With camera_info, a sensor_msgs/CameraInfo goes on T (sensor data QoS)
just before every frame, under the frame's stamp, as a camera driver publishes it. OUT: {"matches": [...], "closures": [...], "poses": [...], "published": n}.
"""

import json
import sys
import time

import rclpy
from rclpy.node import Node
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy, qos_profile_sensor_data
from semlook_msgs.msg import LoopClosure, PlaceMatch
from sensor_msgs.msg import CameraInfo, CompressedImage, Image


def as_dict(m):
    return {
        "sec": m.header.stamp.sec,
        "nanosec": m.header.stamp.nanosec,
        "frame_id": m.header.frame_id,
        "frame": m.frame,
        "place_id": m.place_id,
        "place_index": m.place_index,
        "score": m.score,
        "sequence_matched": m.sequence_matched,
        "sequence_id": m.sequence_id,
        "sequence_score": m.sequence_score,
        "uniqueness": m.uniqueness,
        "accepted": m.accepted,
        "top_ids": list(m.top_ids),
        "top_indices": [int(v) for v in m.top_indices],
        "top_scores": [float(v) for v in m.top_scores],
        "inliers": m.inliers,
        "map_generation": m.map_generation,
        "latency_ms": m.latency_ms,
        "has_relative_pose": m.has_relative_pose,
        "relative_rotation": [float(v) for v in m.relative_rotation],
        "relative_translation": [float(v) for v in m.relative_translation],
        "relative_rotation_deg": m.relative_rotation_deg,
        "pose_inliers": m.pose_inliers,
    }


def pose_dict(m):
    p, o = m.pose.position, m.pose.orientation
    return {
        "sec": m.header.stamp.sec,
        "nanosec": m.header.stamp.nanosec,
        "frame_id": m.header.frame_id,
        "position": [p.x, p.y, p.z],
        "orientation": [o.x, o.y, o.z, o.w],
    }


def main(plan_path, out_path):
    plan = json.load(open(plan_path))
    rclpy.init()
    node = Node("semlook_test_peer")
    raw = node.create_publisher(Image, "/camera/image_raw", qos_profile_sensor_data)
    comp = node.create_publisher(CompressedImage, "/camera/image_raw/compressed", qos_profile_sensor_data)
    cam = plan.get("camera_info")
    info_pub = node.create_publisher(CameraInfo, cam["topic"], qos_profile_sensor_data) if cam else None
    matches, closures, poses = [], [], []
    reliable = QoSProfile(
        reliability=QoSReliabilityPolicy.RELIABLE,
        durability=QoSDurabilityPolicy.VOLATILE,
        history=QoSHistoryPolicy.KEEP_LAST,
        depth=100,
    )
    node.create_subscription(PlaceMatch, "/semlook/match", lambda m: matches.append(as_dict(m)), reliable)
    node.create_subscription(LoopClosure, "/semlook/closure", lambda m: closures.append({"query_id": m.query_id, "place_id": m.place_id}), reliable)
    node.create_subscription(PoseStamped, "/semlook/pose", lambda m: poses.append(pose_dict(m)), reliable)
    deadline = time.time() + plan.get("timeout", 120)
    # discovery: the node subscribes our topics and publishes its matches
    while time.time() < deadline and (raw.get_subscription_count() == 0 or comp.get_subscription_count() == 0 or node.count_publishers("/semlook/match") == 0 or node.count_publishers("/semlook/pose") == 0):
        rclpy.spin_once(node, timeout_sec=0.1)
    if time.time() >= deadline:
        print("peer: the node was not discovered", file=sys.stderr)
        sys.exit(3)
    # a moment for the match subscription to be matched on the node's side too
    t = time.time() + 1.0
    while time.time() < t:
        rclpy.spin_once(node, timeout_sec=0.05)
    published = 0
    for f in plan["frames"]:
        data = open(f["file"], "rb").read() if f.get("file") else b""
        if f["kind"] in ("jpeg", "png", "tiff"):
            m = CompressedImage()
            m.format = f["kind"]
            m.data = data
            pub = comp
        else:
            m = Image()
            m.width, m.height, m.encoding, m.is_bigendian = f["width"], f["height"], f["kind"], 0
            m.step = f["width"] * {"rgb8": 3, "bgr8": 3, "mono8": 1, "16UC1": 2}[f["kind"]]
            m.data = data
            pub = raw
        m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id = f["sec"], f["nanosec"], "cam0"
        if info_pub is not None:
            info = CameraInfo()
            info.header = m.header
            info.width, info.height, info.distortion_model = cam["width"], cam["height"], cam.get("distortion_model", "")
            info.d, info.k = [float(v) for v in cam.get("d", [])], [float(v) for v in cam["k"]]
            info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            k = info.k
            info.p = [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
            info_pub.publish(info)
        before = len(matches)
        pub.publish(m)
        published += 1
        if plan.get("wait") and f.get("answered", True):
            t = time.time() + 60
            while len(matches) == before and time.time() < t:
                rclpy.spin_once(node, timeout_sec=0.05)
        else:
            rclpy.spin_once(node, timeout_sec=0.0)
    while len(matches) < plan.get("expect", 0) and time.time() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    # late answers of a burst
    t = time.time() + plan.get("linger", 0.5)
    while time.time() < t:
        rclpy.spin_once(node, timeout_sec=0.05)
    json.dump({"matches": matches, "closures": closures, "poses": poses, "published": published}, open(out_path, "w"))
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
