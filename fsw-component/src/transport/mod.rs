//! Bus transports: SocketCAN (classic and FD) and UDP sockets.
