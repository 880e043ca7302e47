"""How the files here were made from opencv_contrib's omni_stereocalib_data.xml (see README.md); run once by hand:
``python tests/data/omnidir_stereo/convert.py PATH/TO/omni_stereocalib_data.xml``."""

import sys
from pathlib import Path

import cv2
import numpy as np

FRAMES = 15  # the first 15 of the 39 stereo views
MM_PER_M = 1000.0

src = cv2.FileStorage(sys.argv[1], cv2.FILE_STORAGE_READ)
here = Path(__file__).parent
obj = src.getNode("objectPoints").at(0).mat().reshape(-1, 3) / MM_PER_M  # the file's units are mm
np.save(here / "object_points.npy", obj)
for cam, key in enumerate(("imagePoints1", "imagePoints2")):
    out = cv2.FileStorage(str(here / f"cam_{cam}.json"), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_JSON)
    for f in range(FRAMES):
        pts = src.getNode(key).at(f).mat().reshape(-1)
        out.startWriteStruct(f"frame_{f}", cv2.FileNode_SEQ)
        for value in pts:
            out.write("", float(value))
        out.endWriteStruct()
    out.release()
