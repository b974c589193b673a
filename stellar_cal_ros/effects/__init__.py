"""effects layer of stellar_cal_ros."""
