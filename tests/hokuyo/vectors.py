"""Known SCIP 2.0 byte strings from real devices."""

# The PP reply of a real UTM-30LX-EW (docs/protocols/hokuyo-scip.md; checksums verified there).
PP_REPLY = (b"PP\n00P\nMODL:UTM-30LX-EW;I\nDMIN:23;7\nDMAX:60000;J\nARES:1440;^\nAMIN:0;?\nAMAX:1080;Z\n"
            b"AFRT:540;0\nSCAN:2400;U\n\n")
