"""What every arena process needs: the service runtime (signals, presence, stats, logging;
:mod:`.service`), the shared command-line options (:mod:`.options`), starting, watching and stopping one
child process (:mod:`.process`), the process supervisor behind ``arena up`` (:mod:`.supervisor`), and the
launcher of a real PX4 SITL (:mod:`.px4_sitl`)."""
