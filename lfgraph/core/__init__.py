"""The foundation every wing stands on: the camera model and lens arithmetic, rigid transforms, the view grid, the
``Calibration`` record and its file, errors, the observer protocol, atomic files and the process pools."""
