"""hydrabench.sensors: stereo camera, lidar, radar, calibration, degradation, the dataset.

`SENSOR_MODEL_VERSION` names the physics of the sensor and degradation models. It is recorded in
every dataset manifest and keys every cache of sensor-derived data; bump it whenever a model's
output changes for the same inputs.
"""

SENSOR_MODEL_VERSION = "3"  # 3: twins of fog, rain and snow frames keep the overcast sky
