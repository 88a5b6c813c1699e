"""A follow-line brain written the Behavior Metrics way, to show that such files run in drivebench unchanged.

Nothing here imports drivebench: the file sees only what Behavior Metrics hands a brain (sensors, actuators, the
GUI handler) and OpenCV. Run it with ``drivebench run --brain examples/behavior_metrics/brain_f1_follow_line.py``.

Per frame: BM's perturbation ``config['ImageTranform']`` (none by default) through ``handler.transform_image``,
then an HSV mask of the red line in the lower half of the RGB camera image (BM's cameras give RGB), the mask's mean
column as the line's position, and a PD on its offset from the image centre (normalised to -1..1 so the gains do not
depend on the camera size). Constant 8 m/s.
"""

import cv2
import numpy as np


class Brain:
    def __init__(self, sensors, actuators, model=None, handler=None, config=None):
        self.camera = sensors.get_camera("camera_0")
        self.motors = actuators.get_motor("motors_0")
        self.handler = handler
        self.config = config or {}
        self.transform = self.config["ImageTranform"]
        self.kp = self.config.get("kp", 2.0)
        self.kd = self.config.get("kd", 3.0)
        self.speed = self.config.get("speed", 8.0)
        self.previous_error = 0.0

    def update_frame(self, frame_id, data):
        if self.handler is not None:
            self.handler.update_frame(frame_id, data)

    def execute(self):
        image = self.handler.transform_image(self.camera.getImage().data, self.transform)
        height, width = image.shape[:2]
        lower = image[height // 2 :]
        hsv = cv2.cvtColor(lower, cv2.COLOR_RGB2HSV)
        mask = cv2.inRange(hsv, (0, 110, 15), (10, 255, 255)) | cv2.inRange(hsv, (170, 110, 15), (179, 255, 255))
        columns = np.nonzero(mask)[1]
        if columns.size == 0:
            error = self.previous_error  # lost the line: keep turning the way we were
        else:
            error = (width / 2.0 - columns.mean()) / (width / 2.0)  # > 0: the line is to the left
        w = self.kp * error + self.kd * (error - self.previous_error)
        self.previous_error = error
        self.motors.sendV(self.speed)
        self.motors.sendW(w)
        self.update_frame("frame_0", mask)
