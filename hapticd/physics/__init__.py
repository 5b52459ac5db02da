"""The tick's physics: the frame, the stages and their one compiled call, the
safety chain, the scene and the compiler that builds the call (hapticd.physics.jit)."""
