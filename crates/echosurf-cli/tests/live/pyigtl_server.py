"""An independent OpenIGTLink peer for `echosurf live`'s end-to-end test: a pyigtl server that streams
the frames the test prepared as IMAGE messages (ImageToReference) at a fixed rate, then collects the
POLYDATA messages echosurf sends back, parses each and writes what it sent and got as JSON.

Usage: pyigtl_server.py PORT FRAMES.bin FRAMES.json RESULT.json DONE
(DONE: a file the test creates once echosurf has exited.)
FRAMES.json: {"width", "height", "fps", "frames": [{"timestamp_s", "ijk_to_world": 16 numbers,
row-major}]}; FRAMES.bin: the frames' 8-bit pixels, frame after frame, rows of `width`.
"""
import json
import os
import struct
import sys
import time

import numpy as np
import pyigtl
import pyigtl.messages as messages

SURFACE_DEVICE = "EchosurfSurface"
received = []


class ParsedPolyData(messages.PolyDataMessage):
    """pyigtl 0.3's POLYDATA unpacking is unfinished (it indexes the header Struct itself); this reads
    the same layout from the OpenIGTLink spec and checks every polygon index against the points."""

    def _unpack_content(self, content):
        header = struct.Struct("> 10I")
        (npoints, _nvert, size_vert, _nlines, size_lines, npolys, size_polys, _nstrips, size_strips,
         _nattr) = header.unpack(content[: header.size])
        at = header.size
        points = np.frombuffer(content[at: at + 12 * npoints], dtype=">f4").reshape(-1, 3)
        at += 12 * npoints + size_vert + size_lines
        words = np.frombuffer(content[at: at + size_polys], dtype=">u4")
        polygons, k = [], 0
        while k < len(words):
            n = int(words[k])
            cell = words[k + 1: k + 1 + n]
            if len(cell) != n or (cell >= npoints).any():
                raise ValueError("polygon %d is malformed" % len(polygons))
            polygons.append(cell)
            k += 1 + n
        if len(polygons) != npolys or len(points) != npoints or not np.isfinite(points).all():
            raise ValueError("POLYDATA counts do not match its sections")
        received.append({"points": int(npoints), "polygons": len(polygons),
                         "triangles": all(len(p) == 3 for p in polygons),
                         "device": self.device_name})
        self.points = points


messages.message_type_to_class_constructor["POLYDATA"] = ParsedPolyData


def main():
    port, bin_path, json_path, result_path, done_path = int(sys.argv[1]), *sys.argv[2:6]
    spec = json.load(open(json_path))
    w, h = spec["width"], spec["height"]
    pixels = np.fromfile(bin_path, dtype=np.uint8).reshape(-1, h, w)
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    print("READY", flush=True)
    deadline = time.time() + 60
    while not server.is_connected():
        if time.time() > deadline:
            sys.exit("no client connected within 60 s")
        time.sleep(0.01)
    sent = []
    period = 1.0 / spec["fps"]
    start = time.time()
    for k, frame in enumerate(spec["frames"]):
        matrix = np.array(frame["ijk_to_world"], dtype=np.float64).reshape(4, 4)
        message = pyigtl.ImageMessage(pixels[k][np.newaxis, :, :], ijk_to_world_matrix=matrix,
                                      timestamp=frame["timestamp_s"], device_name="Image_Reference")
        # What a receiver decodes from these bytes, by pyigtl's own unpacking.
        packed = message.pack()
        back = pyigtl.ImageMessage()
        back.unpack(messages.MessageBase.parse_header(packed[:58]), packed[58:])
        sent.append({"ijk_to_world": back.ijk_to_world_matrix.reshape(-1).tolist(),
                     "timestamp_s": back.timestamp})
        server.send_message(message, wait=True)
        next_at = start + (k + 1) * period
        time.sleep(max(0.0, next_at - time.time()))
    stream_s = time.time() - start
    # The final surface comes after the last frame: wait until echosurf has exited (DONE then holds
    # the final mesh's triangle count), then until that surface has been received and parsed.
    deadline = time.time() + 600
    while not os.path.exists(done_path) and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.1)
    final_triangles = int(open(done_path).read() or 0)
    deadline = time.time() + 60
    while time.time() < deadline and not (received and received[-1]["polygons"] == final_triangles):
        time.sleep(0.05)
    json.dump({"sent": sent, "stream_s": stream_s, "polydata": received}, open(result_path, "w"))
    server.stop()


if __name__ == "__main__":
    main()
