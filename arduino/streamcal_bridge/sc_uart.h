// sc_uart.h -- USART0 at 8N1 with interrupt-driven 64-byte receive and transmit rings, for the
// sketch's frames. Replaces HardwareSerial (Stream/Print virtuals, begin() for every frame format:
// ~0.7 KB flash the sketch does not need). Same baud setting as HardwareSerial::begin (U2X, so
// 115200 at 16 MHz is UBRR 16, +2.1 %), and like it a full receive ring drops the new byte.
#ifndef SC_UART_H
#define SC_UART_H

#include <avr/interrupt.h>
#include <avr/io.h>

#define SC_UART_RING 64   // bytes, a power of two

static volatile uint8_t sc_rx_ring[SC_UART_RING], sc_tx_ring[SC_UART_RING];
static volatile uint8_t sc_rx_head, sc_rx_tail, sc_tx_head, sc_tx_tail;

ISR(USART_RX_vect) {
  uint8_t c = UDR0, h = (uint8_t)((sc_rx_head + 1) & (SC_UART_RING - 1));
  if (h != sc_rx_tail) {
    sc_rx_ring[sc_rx_head] = c;
    sc_rx_head = h;
  }
}

ISR(USART_UDRE_vect) {
  uint8_t t = sc_tx_tail;
  if (t == sc_tx_head) {
    UCSR0B &= (uint8_t)~_BV(UDRIE0);
    return;
  }
  UDR0 = sc_tx_ring[t];
  sc_tx_tail = (uint8_t)((t + 1) & (SC_UART_RING - 1));
}

static void sc_uart_begin(uint32_t baud) {
  UCSR0A = _BV(U2X0);
  UBRR0 = (uint16_t)((F_CPU / 4 / baud - 1) / 2);
  UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);   // 8N1
  UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

// Bytes the transmit ring can take now.
static uint8_t sc_uart_room() {
  return (uint8_t)((sc_tx_tail - sc_tx_head - 1) & (SC_UART_RING - 1));
}

// Queue one byte; the caller checked sc_uart_room().
static void sc_uart_put(uint8_t c) {
  uint8_t h = sc_tx_head;
  sc_tx_ring[h] = c;
  sc_tx_head = (uint8_t)((h + 1) & (SC_UART_RING - 1));
  UCSR0B |= _BV(UDRIE0);
}

// Next received byte, or -1.
static int16_t sc_uart_get() {
  uint8_t t = sc_rx_tail;
  if (t == sc_rx_head) return -1;
  uint8_t c = sc_rx_ring[t];
  sc_rx_tail = (uint8_t)((t + 1) & (SC_UART_RING - 1));
  return c;
}

#endif  // SC_UART_H
