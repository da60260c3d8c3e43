"""The HTTP service: the app and its start-up here; its layers in http/, body/, pipeline/ and routers/."""
