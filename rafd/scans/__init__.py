"""Scan formats in one place: each form a Navtech scan is stored in, how it is read and how it becomes RADIATE's
Cartesian grid, side by side (numpy + opencv, no torch: the service decodes posted scans with them).

- `cartesian.py`: RADIATE's Cartesian scans (`Navtech_Cartesian/NNNNNN.png`, uint8 [1152, 1152], the radar at the
  centre), the form every other one becomes and the model's crop is cut from (rafd.preprocess): reading a scan PNG
  (its grey pixels; its size from the header alone) and the Cartesian sides a model accepts.
- `polar.py`: RADIATE's polar scans (`Navtech_Polar/NNNNNN.png`, uint8 [576 range bins, 400 azimuths]): their
  conventions, polar -> Cartesian (opencv remap), another sensor's polar scan resampled onto RADIATE's, and a polar
  scan file read as a Cartesian scan (PolarSource).
- `native.py`: the sensor's own layout, as the Oxford Radar RobotCar and Boreas datasets store it
  (`radar/<UNIX microseconds>.png`, one row per azimuth: timestamp, encoder angle, valid flag, range bins): the
  header parsed and checked against a real sensor's, the per-dataset formats and accepted sizes, native -> Cartesian,
  and a native scan file read as a Cartesian scan (NativeSource).

Which files a sequence folder holds is rafd.data's (rafd.data.folders, rafd.data.native_folder); decoding a posted
body is the service's (service/body/images.py). For the layer order (tests/test_layers.py) this package is part of
rafd's core, with the top-level modules: rafd.preprocess's one path to the model input starts with its polar
conversion, and it builds on rafd.geometry.
"""
