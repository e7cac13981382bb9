"""The cell over OPC UA, for the MES and the line PLC: an asyncua server the daemon starts when the cell
file says `opcua: {enabled: true}`. `address_space` lays out Objects/Cell, `security` says who may do
what, `server` serves the service's verbs as methods and follows the cell into variables and events."""
