"""MuJoCo simulation of a differential-drive robot, bridged to ROS 2 topics, in three worlds.

Worlds (``sim.worlds``): ``office_small``, ``workshop``, ``real_room``. Sensors are ray casts
(``mujoco.mj_multiRay``, no OpenGL): a 360-beam 2D lidar, a 96x56 depth camera with the
RealSense D435's field of view, range and noise, wheel odometry with drift, ground truth.
``sim.bridge`` runs it in real time and publishes ``/scan``, ``/camera/depth/points``,
``/odom``, ``/ground_truth/pose``, ``/clock``...; ``sim.cli`` is ``rory sim``. Everything is
documented in ``sim/README.md``.

Importing ``sim`` or its non-ROS modules (worlds, model, robot, sensors, simulation, maps,
render, driver's control law) does not import rclpy.
"""
