"""The replan monitor's parts (the node is :mod:`psprm_ros.replan_monitor`): the input gate that checks and forwards
every input (:mod:`.inputs`) and the triggers that ask the server for a plan or a stop (:mod:`.triggers`)."""
