MIN_OPSET = 17  # GridSample needs opset 16; the project targets 17+
