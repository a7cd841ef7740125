"""MuJoCo simulation of a differential-drive robot bridged to ROS 2 (not written yet).

See the simulator issue: three worlds (office_small, workshop, real_room), lidar, depth camera,
odometry and ground truth from mujoco.mj_multiRay, /cmd_vel and /e_stop.
"""
