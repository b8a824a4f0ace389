"""The ROS 2 adapter: the twin node, its parameters, the recorder, the test harness, examples.

Holds the node (:mod:`.node`) and its parameters (:mod:`.params`), the in-node MCAP
recorder (:mod:`.recorder`), :class:`~.testing.TwinHarness` for controller tests on
isolated ROS domains (:mod:`.testing`), the example wave controller
(:mod:`.wave_controller`), the demo that runs both (:mod:`.demo`) and the shared
``main()`` of the executables (:mod:`.spin`).  Callbacks only translate messages:
numerics stay in :mod:`dea_array_twin.model`.  May import rclpy, the model, the config
file reader and :mod:`dea_array_twin.bag`; nothing above.
"""
