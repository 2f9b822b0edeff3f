"""Robot backends behind one interface: the kinematic simulator and the JRC link."""
