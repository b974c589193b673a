"""io layer of stellar_cal_ros."""
