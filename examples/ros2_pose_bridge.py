#!/usr/bin/env python3
"""A ROS 2 node that republishes the lino-loc daemon's ZeroMQ pose stream as /amcl_pose.

Runs on a machine with ROS 2 (rclpy, geometry_msgs) and pyzmq; the robot's lino-loc install
needs neither. It subscribes to the daemon's ``pose`` topic (docs/zeromq.md: two frames,
``[b"pose", json]``) and publishes each pose as geometry_msgs/msg/PoseWithCovarianceStamped,
frame ``map``, the stamp the frame's capture time, the 3 x 3 covariance over (x, y, theta)
placed in the 6 x 6 one over (x, y, z, rot x, rot y, rot z) at rows and columns 0, 1, 5 (z,
roll, pitch 0, as nav2's AMCL does), with AMCL's QoS (reliable, transient local, depth 1)::

    python3 ros2_pose_bridge.py --ros-args -p endpoint:=tcp://127.0.0.1:5556 -p topic:=/amcl_pose

It does not broadcast map -> odom on /tf (that needs the robot's odom -> base_link from tf2:
map -> odom = pose * inverse(odom -> base_link) at the pose's stamp, REP-105).
"""

from __future__ import annotations

import json
import math

ENDPOINT = "tcp://127.0.0.1:5556"
#: Where x, y and theta sit in the 6 x 6 covariance (x, y, z, rot x, rot y, rot z).
COV_INDEX = (0, 1, 5)


def pose_fields(msg: dict) -> dict:
    """The PoseWithCovarianceStamped fields of a daemon ``pose`` message (plain values)."""
    ns = round(float(msg["stamp"]) * 1e9)
    p, c = msg["pose"], [float(v) for v in msg["covariance"]]
    cov = [0.0] * 36
    for i, a in enumerate(COV_INDEX):
        for j, b in enumerate(COV_INDEX):
            cov[6 * a + b] = c[3 * i + j]
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000, "frame_id": msg.get("frame_id", "map"),
            "x": float(p["x"]), "y": float(p["y"]), "qz": math.sin(p["theta"] / 2),
            "qw": math.cos(p["theta"] / 2), "covariance": cov}


def main() -> None:
    import rclpy
    import zmq
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    class PoseBridge(Node):
        def __init__(self) -> None:
            super().__init__("lino_loc_pose_bridge")
            endpoint = self.declare_parameter("endpoint", ENDPOINT).value
            topic = self.declare_parameter("topic", "/amcl_pose").value
            qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.pub = self.create_publisher(PoseWithCovarianceStamped, topic, qos)
            self.sub = zmq.Context.instance().socket(zmq.SUB)
            self.sub.connect(endpoint)
            self.sub.setsockopt(zmq.SUBSCRIBE, b"pose")
            self.create_timer(0.005, self.poll)  # drain the socket 200 times a second

        def poll(self) -> None:
            while self.sub.poll(0):
                topic, payload = self.sub.recv_multipart()
                if topic != b"pose":  # SUB filters by prefix
                    continue
                try:
                    f = pose_fields(json.loads(payload))
                except (ValueError, KeyError, TypeError) as exc:
                    self.get_logger().warning(f"bad pose message skipped: {exc}")
                    continue
                out = PoseWithCovarianceStamped()
                out.header.stamp.sec, out.header.stamp.nanosec = f["sec"], f["nanosec"]
                out.header.frame_id = f["frame_id"]
                out.pose.pose.position.x, out.pose.pose.position.y = f["x"], f["y"]
                out.pose.pose.orientation.z, out.pose.pose.orientation.w = f["qz"], f["qw"]
                out.pose.covariance = f["covariance"]
                self.pub.publish(out)

    rclpy.init()
    node = PoseBridge()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
