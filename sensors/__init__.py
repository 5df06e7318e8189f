"""hydrabench.sensors: stereo camera, lidar, radar, calibration, degradation, the dataset.

`SENSOR_MODEL_VERSION` names the physics of the sensor and degradation models. It is recorded in
every dataset manifest and keys every cache of sensor-derived data; bump it whenever a model's
output changes for the same inputs.
"""

# 3: twins of fog, rain and snow frames keep the overcast sky
# 4: the camera's code pass is drawn single-sampled (sensors.camera._single_sample): depth is rounded
#    differently (~1e-5 relative), which moves surface normals at some edges (~2 % of pixels)
SENSOR_MODEL_VERSION = "4"
