"""Recorded runs re-simulated and shown: offline replay with FIT, realtime republishing, plots.

Holds the offline replay of a bag's commands through the twin (:mod:`.offline`), the
realtime republisher (:mod:`.realtime`, rclpy imported when it runs) and the plot of a
bag (:mod:`.plot`, matplotlib imported when it draws).  May import the model, the bag
layer and the ROS adapter's message helpers; not the studies, calibration or CLI.
"""
