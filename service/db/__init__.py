"""DB models, sessions and the CRUD functions shared by the API, the worker and beat."""
