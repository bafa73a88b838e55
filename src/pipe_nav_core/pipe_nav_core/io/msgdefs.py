"""The ros2msg definitions and RIHS01 type hashes of the message types PipeNav writes
(sensor_msgs Imu, MagneticField, NavSatFix; nav_msgs Odometry, Path; geometry_msgs PoseArray),
as ROS 2 Jazzy records them in a bag's schemas and channel metadata.

They are what rosbags' Jazzy typestore generates (``generate_msgdef(t, ros_version=2)[0]``,
``hash_rihs01(t)``; tests/unit/test_io_cdr.py checks they still are), stored here because building
that typestore costs about 0.1 s, a tenth of smoothing a short run. A definition is the type's
own fields, then each type it uses after a separator line; each type's own fields are stored
once (``_FIELDS``, a line each). Other types are still generated (io/bagwrite.py).
"""

_SEPARATOR = "=" * 80 + "\nMSG: "

# fmt: off
_FIELDS: dict[str, tuple[str, ...]] = {
    'sensor_msgs/Imu': (
        'std_msgs/Header header',
        'geometry_msgs/Quaternion orientation',
        'float64[9] orientation_covariance',
        'geometry_msgs/Vector3 angular_velocity',
        'float64[9] angular_velocity_covariance',
        'geometry_msgs/Vector3 linear_acceleration',
        'float64[9] linear_acceleration_covariance',
    ),
    'std_msgs/Header': (
        'builtin_interfaces/Time stamp',
        'string frame_id',
    ),
    'builtin_interfaces/Time': (
        'int32 sec',
        'uint32 nanosec',
    ),
    'geometry_msgs/Quaternion': (
        'float64 x',
        'float64 y',
        'float64 z',
        'float64 w',
    ),
    'geometry_msgs/Vector3': (
        'float64 x',
        'float64 y',
        'float64 z',
    ),
    'nav_msgs/Odometry': (
        'std_msgs/Header header',
        'string child_frame_id',
        'geometry_msgs/PoseWithCovariance pose',
        'geometry_msgs/TwistWithCovariance twist',
    ),
    'geometry_msgs/PoseWithCovariance': (
        'geometry_msgs/Pose pose',
        'float64[36] covariance',
    ),
    'geometry_msgs/Pose': (
        'geometry_msgs/Point position',
        'geometry_msgs/Quaternion orientation',
    ),
    'geometry_msgs/Point': (
        'float64 x',
        'float64 y',
        'float64 z',
    ),
    'geometry_msgs/TwistWithCovariance': (
        'geometry_msgs/Twist twist',
        'float64[36] covariance',
    ),
    'geometry_msgs/Twist': (
        'geometry_msgs/Vector3 linear',
        'geometry_msgs/Vector3 angular',
    ),
    'sensor_msgs/MagneticField': (
        'std_msgs/Header header',
        'geometry_msgs/Vector3 magnetic_field',
        'float64[9] magnetic_field_covariance',
    ),
    'sensor_msgs/NavSatFix': (
        'uint8 COVARIANCE_TYPE_UNKNOWN=0',
        'uint8 COVARIANCE_TYPE_APPROXIMATED=1',
        'uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN=2',
        'uint8 COVARIANCE_TYPE_KNOWN=3',
        'std_msgs/Header header',
        'sensor_msgs/NavSatStatus status',
        'float64 latitude',
        'float64 longitude',
        'float64 altitude',
        'float64[9] position_covariance',
        'uint8 position_covariance_type',
    ),
    'sensor_msgs/NavSatStatus': (
        'int8 STATUS_UNKNOWN=-2',
        'int8 STATUS_NO_FIX=-1',
        'int8 STATUS_FIX=0',
        'int8 STATUS_SBAS_FIX=1',
        'int8 STATUS_GBAS_FIX=2',
        'uint16 SERVICE_UNKNOWN=0',
        'uint16 SERVICE_GPS=1',
        'uint16 SERVICE_GLONASS=2',
        'uint16 SERVICE_COMPASS=4',
        'uint16 SERVICE_GALILEO=8',
        'int8 status',
        'uint16 service',
    ),
    'nav_msgs/Path': (
        'std_msgs/Header header',
        'geometry_msgs/PoseStamped[] poses',
    ),
    'geometry_msgs/PoseStamped': (
        'std_msgs/Header header',
        'geometry_msgs/Pose pose',
    ),
    'geometry_msgs/PoseArray': (
        'std_msgs/Header header',
        'geometry_msgs/Pose[] poses',
    ),
}

# the types each written type uses, in the order its definition lists them
_USES: dict[str, tuple[str, ...]] = {
    'sensor_msgs/msg/Imu': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'geometry_msgs/Quaternion',
        'geometry_msgs/Vector3',
    ),
    'nav_msgs/msg/Odometry': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'geometry_msgs/PoseWithCovariance',
        'geometry_msgs/Pose', 'geometry_msgs/Point', 'geometry_msgs/Quaternion',
        'geometry_msgs/TwistWithCovariance', 'geometry_msgs/Twist', 'geometry_msgs/Vector3',
    ),
    'sensor_msgs/msg/MagneticField': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'geometry_msgs/Vector3',
    ),
    'sensor_msgs/msg/NavSatFix': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'sensor_msgs/NavSatStatus',
    ),
    'nav_msgs/msg/Path': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'geometry_msgs/PoseStamped',
        'geometry_msgs/Pose', 'geometry_msgs/Point', 'geometry_msgs/Quaternion',
    ),
    'geometry_msgs/msg/PoseArray': (
        'std_msgs/Header', 'builtin_interfaces/Time', 'geometry_msgs/Pose', 'geometry_msgs/Point',
        'geometry_msgs/Quaternion',
    ),
}

HASHES: dict[str, str] = {
    'sensor_msgs/msg/Imu':
        'RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b',
    'nav_msgs/msg/Odometry':
        'RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0',
    'sensor_msgs/msg/MagneticField':
        'RIHS01_e80f32f56a20486c9923008fc1a1db07bbb273cbbf6a5b3bfa00835ee00e4dff',
    'sensor_msgs/msg/NavSatFix':
        'RIHS01_62223ab3fe210a15976021da7afddc9e200dc9ec75231c1b6a557fc598a65404',
    'nav_msgs/msg/Path':
        'RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b',
    'geometry_msgs/msg/PoseArray':
        'RIHS01_af0cc36d190e104d546d168d6b39df04fa4b4ccecf59cb4c9ed328d3d5004aa0',
}
# fmt: on


DEFINITIONS: dict[str, str] = {
    name: "\n".join(_FIELDS[name.replace("/msg/", "/")])
    + "".join(f"\n{_SEPARATOR}{used}\n" + "\n".join(_FIELDS[used]) for used in uses)
    + "\n"
    for name, uses in _USES.items()
}
