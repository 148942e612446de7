"""Frame loops around a `Frontend`: a sequence fed to it (`runner`) and the frontend in a child
process (`process`)."""
