"""`make demo`: a master and a robot agent on this one machine (loopback, no VPN), paired, ready to explore."""
