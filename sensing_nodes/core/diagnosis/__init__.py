"""sensing_doctor's checks: plain functions over arrays, by concern (timing, imu, wheels, laser,
covariance, tf), each returning Check records (core/diagnosis/check.py). No rclpy, no messages,
no files: tools/doctor.py reads the bag (bags/survey.py) and writes the report."""
