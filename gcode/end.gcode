; crispen end code (Marlin, Ultimaker 2): heaters and fan off, present the print.
; crispen fills in how far to lower the bed (clear of the print, within the machine).
M104 S0 ; nozzle heater off
M140 S0 ; bed heater off
M107 ; part fan off
G91 ; relative moves
G1 E-1 F300 ; release pressure
G1 Z5 E-5 F3000 ; lift off the print and retract further
G90 ; absolute moves
G28 X0 Y0 ; park the head at the back left, away from the print
G1 Z{PRESENT_Z} F900 ; lower the bed so the print can be taken off
M84 ; motors off
M117 Print done
; end of crispen end code
