"""sensing_doctor's work: a robot's bag diagnosed without ground truth (diagnosis), a preset for
this package's nodes written from what was found (preset), that preset run over the bag through
the nodes offline (fused), and the report (report). tools/doctor.py is the command."""
