"""The service around the servo loop: the session built from a profile, the control
server, the run summary and the service manager's notifications."""
