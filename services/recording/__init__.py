"""Recording and replay: one MCAP file per session, the Localizer run again on it.

- :mod:`services.recording.channels`: the topics, their schemas and message encodings (the
  one channel layer, shared by the recording, the replay's output and a live viewer);
- :mod:`services.recording.image_codec`: the camera image as PNG, the disparity map as a
  16-bit image with its scale (both lossless);
- :mod:`services.recording.foxglove_messages`: Foxglove messages of an estimate (pose,
  covariance ellipse, particles, the head's transform);
- :mod:`services.recording.session_file`: one MCAP file (chunked, indexed, flushed, rotated);
- :mod:`services.recording.recorder`: ``[recording]`` and the daemon's recorder (a bounded
  queue to a writer thread);
- :mod:`services.recording.recording_reader`: reading a recording, also one cut by a kill -9;
- :mod:`services.replay`: the Localizer on a recording's inputs, as fast as it can.

mcap and foxglove-sdk are the optional ``viz`` extra: :func:`services.recording.channels.require_viz`
says so in one line when they are missing. docs/recording.md describes the file.
"""
