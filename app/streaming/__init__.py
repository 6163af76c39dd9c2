"""Live streams of the captured people to other tools (the streamer worker's cores, no bus
here): the humanoid bones VMC carries (:mod:`.humanoid`), OSC packets (:mod:`.osc`), the
Lab Streaming Layer outlet (:mod:`.lsl`) and person slots (:mod:`.slots`)."""
