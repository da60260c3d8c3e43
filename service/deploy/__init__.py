"""Scale-out: nginx.conf (sticky on the stream), compose.yaml, a loopback harness and its benchmark."""
