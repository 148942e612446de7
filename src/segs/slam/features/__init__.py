"""Per frame, ahead of tracking: ORB features, stereo matches and depths of a frame (`FrameBuilder`
-> `SlamFrame`), built in the frame reader's process by `OrbFrontend.preparer()`."""
