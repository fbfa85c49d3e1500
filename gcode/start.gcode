; crispen start code (Marlin, Ultimaker 2 over USB): heat, home, prime.
; crispen fills in the bed and nozzle temperatures per job.
G21 ; millimetres
G90 ; absolute positioning
M82 ; absolute extrusion
M107 ; part fan off
M140 S{BED_TEMP} ; start heating the bed
M104 S{NOZZLE_TEMP} ; start heating the nozzle while homing
G28 ; home all axes
G1 X15 Y5 Z15 F6000 ; front left corner, nozzle clear of the glass
M190 S{BED_TEMP} ; wait for the bed
M109 S{NOZZLE_TEMP} ; wait for the nozzle
G92 E0
G1 F200 E10 ; prime: push out filament that oozed during heating
G92 E0
M117 Printing...
; end of crispen start code
