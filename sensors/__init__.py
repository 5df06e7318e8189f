"""hydrabench.sensors: stereo camera, lidar, radar, calibration, degradation, the dataset.

`SENSOR_MODEL_VERSION` names the physics of the sensor and degradation models. It is recorded in
every dataset manifest and keys every cache of sensor-derived data; bump it whenever a model's
output changes for the same inputs.
"""

# 3: twins of fog, rain and snow frames keep the overcast sky
# 4: the camera's code pass is drawn single-sampled (sensors.camera._single_sample): depth is rounded
#    differently (< 2e-4 relative), which moves surface normals at some edges (radiance changes at
#    ~1-2 % of pixels); where that moves the exposure or the Poisson/normal split of a pixel, the
#    sensor noise of the frame is drawn anew (same statistics, another sample)
SENSOR_MODEL_VERSION = "4"
