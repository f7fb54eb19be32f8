"""pybullet landing world (scene generator, multirotor, velocity flight controller, turbulence, RGB-D camera,
landing judge), simulated pilot and MAVLink vehicle stand-in."""
