"""sim layer of stellar_cal_ros."""
