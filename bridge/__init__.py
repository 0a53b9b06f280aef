"""The MAVLink layer every quadsr process shares: links, messages, lockstep stepping, logs, signing.

bridge imports none of sitl, identification or controller.
"""
